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
# # Front pushing: a Monte Carlo and its convergence plot
#
# The front-push task pushes a sphere towards a goal 750 µm away, measures where it came to rest,
# and corrects the next attempt with the learning law of eq 13,
# $\delta(j+1) = \delta(j) + K_c\,e(j)$, until the error is within $\varepsilon_p = 75$ µm (eq 12).
# What varies from trial to trial is the sphere's release displacement $D_{p,r}$ after the robot
# stops (§IV-D; here the calibrated model with 10 % scatter). The iteration-domain analysis
# predicts a pole at $1 - K_c$: $K_c = 1$ is dead-beat, $K_c = 0$ never learns.
#
# Each trial is the closed loop the rig runs (controller → coils → robot → fluid-coupled sphere →
# camera → tracker → servo), stepped for all trials at once. The trial function is the one the
# `front-push` study uses; run through `magctl.sweep.run_sweeps`, trial *k*'s result does not depend
# on the batch or the executor. A small number of trials keeps the notebook quick; `magctl study
# front-push` runs 100 per controller.

# %%
import matplotlib.pyplot as plt
import numpy as np

from magctl.control.status import Status
from magctl.loops import Experiment, Variability
from magctl.studies.push import controller_summary
from magctl.studies.trials import run_push_trials
from magctl.sweep import run_sweeps

TRIALS = 8
SEED = 0
plant = Variability(release_scatter=0.1)
experiments = {f"K_c={kc:g}": Experiment("front", task={"kc": kc, "delta0": 0.0}, max_frames=4000,
                                         variability=plant, label=f"K_c={kc:g}")
               for kc in (0.0, 0.5, 1.0)}

# the three controllers' trials as one sweep, in this process (scheduler=None would use local processes,
# a Dask address a cluster: the same numbers, trial for trial)
jobs = {label: (run_push_trials, TRIALS, {"exp": exp}) for label, exp in experiments.items()}
runs = run_sweeps(jobs, seed=SEED, chunk_size=TRIALS, scheduler="serial", progress=False)
summaries = {label: controller_summary(r) for label, r in runs.items()}
for label, s in summaries.items():
    print(f"{label}: {100 * s['converged_fraction']:.0f} % converged, mean attempts "
          f"{s['mean_attempts_all']:.1f}, final error median {s['final_error_um_median']:.0f} µm")

# %% [markdown]
# ## Convergence plot (cf. Fig 10)
#
# The fraction of trials that have met eq 12 after each attempt.

# %%
fig, ax = plt.subplots(figsize=(6.4, 4))
for label, s in summaries.items():
    by_attempt = 100 * np.asarray(s["converged_by_attempt"])
    ax.step(np.arange(1, len(by_attempt) + 1), by_attempt, where="post", label=label)
ax.set_xlabel("pushing attempts")
ax.set_ylabel("converged trials (%)")
ax.set_ylim(-2, 102)
ax.grid(alpha=0.3)
ax.legend(loc="lower right")
plt.show()

# %% [markdown]
# ## Error after each attempt
#
# The learning law's error sequence $e(j)$ of trial 0 of each controller: $K_c = 1$ removes the
# release offset in one step, $K_c = 0.5$ halves it each attempt, $K_c = 0$ keeps it.

# %%
fig, ax = plt.subplots(figsize=(6.4, 3.6))
for label, r in runs.items():
    err = np.asarray(r["error_um"][0])
    ax.plot(np.arange(err.size), err, marker="o", label=label)
ax.axhline(75, color="k", ls=":", lw=0.8, label="ε_p = 75 µm")
ax.set_xlabel("attempt j")
ax.set_ylabel("|error| (µm)")
ax.legend()
plt.show()

# %% [markdown]
# The learning controllers converge and the naïve one does not, as the pole $1 - K_c$ says:

# %%
assert summaries["K_c=1"]["converged_fraction"] > summaries["K_c=0"]["converged_fraction"]
{label: dict(zip(*np.unique([Status(s).label for s in r["status"]], return_counts=True), strict=True))
 for label, r in runs.items()}
