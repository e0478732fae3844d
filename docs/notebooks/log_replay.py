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
# # Replaying a rig log
#
# `magctl rig run --log run.jsonl` writes a run log: a start document (task, options, seed, the
# parameter files the run used), a descriptor (every field with its unit), one event per 30 Hz
# frame (what the rig observed, what the controller commanded, the task's outputs, timing) and a
# stop document. Replaying feeds the logged observations through a controller rebuilt from the
# start document and compares its commands with the logged ones: the same controller gives the
# same commands, bit for bit.
#
# Here the rig is the in-process simulated rig with the kinematic stand-in plant, run back to back
# rather than at 30 Hz, so the notebook makes its own log in a second or two. A log from a real rig
# is read the same way.

# %%
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from magctl.rig.log import read_log, replay
from magctl.rig.runtime import Runtime
from magctl.rig.sim import SimRig

folder = Path(tempfile.mkdtemp())
log_path = folder / "run.jsonl"
rig = SimRig(n_spheres=1, realtime=False, seed=0, plant="standin")
try:
    report = Runtime(rig, "front-push", {}, log_path=log_path, realtime=False, max_ticks=600, seed=0,
                     quiet=True, rig_description={"kind": "SimRig", "plant": "standin"}).run()
finally:
    rig.close()
report.stats()["exit_status"], report.stats()["ticks"]

# %% [markdown]
# ## What the log holds
#
# `read_log` checks every document against the schema; `summary()` is what `magctl log show`
# prints (positions in µm, status and phase by name).

# %%
log = read_log(log_path)
summary = log.summary()
{k: summary[k] for k in ("task", "events", "exit_status", "final_robot_um", "final_spheres_um", "final_outputs")}

# %%
t = np.array([e["obs"]["t_s"] for e in log.events])
robot = np.array([e["obs"]["robot_est_m"] for e in log.events]) * 1e6
sphere = np.array([e["obs"]["spheres_est_m"][0] for e in log.events]) * 1e6
goal = np.asarray(log.start["options"]["goal_m"]) * 1e6
attempt = np.array([e["outputs"]["attempt"] for e in log.events])

fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(9, 3.6))
ax0.plot(robot[:, 0], robot[:, 1], lw=0.8, label="robot")
ax0.plot(sphere[:, 0], sphere[:, 1], lw=2, label="sphere")
ax0.plot(*goal, "k+", ms=12, label="goal")
ax0.set_xlabel("x (µm)")
ax0.set_ylabel("y (µm)")
ax0.set_aspect("equal", adjustable="datalim")
ax0.legend(fontsize=8)
ax1.plot(t, np.linalg.norm(sphere - goal, axis=1), label="sphere to goal")
ax1.step(t, 100 * attempt, where="post", lw=0.8, label="attempt × 100")
ax1.set_xlabel("time (s)")
ax1.set_ylabel("µm")
ax1.legend(fontsize=8)
plt.show()

# %% [markdown]
# ## Replay
#
# The controller rebuilt from the start document (with the parameter files the run used) sees the
# logged observations frame by frame; every command it gives must equal the logged one.

# %%
result = replay(log_path)
print(f"{result.compared} commands compared, {result.mismatches} mismatches")
assert result.identical and result.compared > 0
