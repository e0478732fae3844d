# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # Designing the 30 Hz visual servo: margins and a Bode plot
#
# The robot is driven to a target by a PI servo that sees it through a camera with two frames of
# lag (paper §II, §VI-A). Along one axis the loop is
#
# $$L(z) = \Big(K_p + \frac{K_i T}{z-1}\Big)\,\frac{T}{z-1}\,z^{-d},\qquad T = 1/30\ \mathrm{s},\ d = 2,$$
#
# PI × robot (speed → position, an integrator) × camera delay. magctl builds this loop from the
# same blocks the simulations run, exports it to python-control, and python-control gives the
# margins, the Bode plot and the closed-loop poles. We compare the two settings of
# `models/servo.toml`: the paper-like one (about 100 µm overshoot on a 1 mm step) and the tuned one
# every controller uses by default.

# %%
import control
import matplotlib.pyplot as plt
import numpy as np

from magctl.control.servo import servo_params
from magctl.core import simulate
from magctl.stability.servo import analyse, loop_transfer, servo_loop_diagram

DELAY = 2
settings = {name: servo_params(name) for name in ("paper", "tuned")}
{name: (p.kp, p.ki) for name, p in settings.items()}

# %% [markdown]
# ## Margins from python-control
#
# `loop_transfer` is `C P z⁻ᵈ` exported from the magctl blocks; `control.margin` reads the gain
# and phase margins off it. The same numbers come out of `analyse`, which `magctl stability servo`
# prints.

# %%
rows = []
for name, p in settings.items():
    L = loop_transfer(p.kp, p.ki, DELAY)
    gm, pm, wcg, wcp = control.margin(L)
    rep = analyse(p.kp, p.ki, DELAY)
    assert np.isclose(pm, rep.phase_margin_deg) and np.isclose(gm, rep.gain_margin)
    rows.append((name, gm, pm, wcp, 100 * rep.overshoot_ratio))
for name, gm, pm, wcp, os_ in rows:
    print(f"{name:6s} gain margin {gm:5.2f}  phase margin {pm:5.1f}°  crossover {wcp:5.2f} rad/s  "
          f"linear overshoot {os_:4.1f} %")

# %% [markdown]
# The tuned loop has no integral action (the robot already integrates speed, so a step target needs
# none) and a phase margin of about 76°: its step response does not overshoot. The paper-like PI has
# less phase margin and overshoots by about 12 % of the step.
#
# ## Bode plot of the loop transfer

# %%
fig = plt.figure(figsize=(7, 5))
for name, p in settings.items():
    control.bode_plot(loop_transfer(p.kp, p.ki, DELAY), omega=np.logspace(-1.5, np.log10(np.pi * 30), 400),
                      label=name, display_margins=False)
fig.suptitle("loop transfer C P z⁻²: paper-like and tuned PI")
plt.show()

# %% [markdown]
# ## Closed loop: poles and the step response
#
# The closed loop `r → x` is the magctl diagram exported with `to_control()`; its poles must lie
# inside the unit circle. A simulated 1 mm step of the same diagram (`simulate`, converted with
# `SimResult.to_control()` into python-control's `TimeResponseData`) and python-control's own
# `step_response` of the exported model agree.

# %%
steps = 120
fig, ax = plt.subplots(figsize=(6.4, 3.6))
for name, p in settings.items():
    loop = servo_loop_diagram(p.kp, p.ki, DELAY)
    sys = loop.to_control()
    print(name, "closed-loop |poles|:", np.round(np.abs(sys.poles()), 4))
    res = simulate(loop, steps, inputs={"r": 1e-3}).to_control(trial=0)
    ref = control.step_response(sys, T=res.time)
    assert np.allclose(res.outputs, 1e-3 * ref.outputs, rtol=1e-9, atol=1e-15)
    ax.plot(res.time, res.outputs * 1e6, label=f"{name}: overshoot {(res.outputs.max() - 1e-3) * 1e6:.0f} µm")
ax.axhline(1000, color="k", lw=0.5)
ax.set_xlabel("time (s)")
ax.set_ylabel("position (µm)")
ax.legend()
plt.show()
