"""Batches of push trials: the closed loop of :func:`magctl.loops.push_loop` stepped in lockstep.

:func:`run_push_trials` steps a batch of trials until every trial has terminated
and reduces each trial to plain numbers (status, attempts, error after every
attempt). It has the signature :func:`magctl.sweep.run_trials` expects, so trials
fan out over local processes or a Dask cluster with identical results.
"""

from __future__ import annotations

import os

import numpy as np

from magctl.control.status import Status
from magctl.core import simulate
from magctl.core.units import UM
from magctl.loops import Experiment, geometry, push_loop
from magctl.plant.fluid.params import sphere_params


def task_error(kind: str, spheres: np.ndarray, goal: np.ndarray, radius: float) -> np.ndarray:
    """Positioning error of the true sphere positions ``(…, N, 2)``: distance to the goal
    (push tasks) or the surface gap between the two spheres (assembly, eq 21)."""
    if kind in ("front", "side", "front-side"):
        return np.linalg.norm(spheres[..., 0, :] - goal, axis=-1)
    return np.linalg.norm(spheres[..., 1, :] - spheres[..., 0, :], axis=-1) - 2 * radius


STATUS, ATTEMPT, CORRECTION = "controller/task.status", "controller/task.attempt", "controller/task.correction"
SPHERES, ROBOT, HEADING = "plant/spheres.spheres", "plant/robot.position", "plant/robot.heading"
RECORD = [STATUS, ATTEMPT, SPHERES, ROBOT, HEADING, CORRECTION]


def study_engine() -> str:
    """The engine the studies' closed loops run on: ``$MAGCTL_ENGINE``, else ``"auto"`` (compiled when every
    block has a kernel — the push loops do — with the interpreted engine's numbers)."""
    return os.environ.get("MAGCTL_ENGINE") or "auto"


def run_push_trials(trials, seed: int, *, exp: Experiment, chunk_frames: int = 150,
                    keep_paths: bool = False) -> dict:
    """Run the given trials of ``exp`` in lockstep until each has terminated.

    Returns per-trial arrays (leading axis = trials): ``status`` (code), ``attempts``,
    ``error_um`` after each attempt (``(B, A)``, NaN where no attempt ran; index 0 is the
    start), ``signed_error_um`` (the same along the initial sphere→goal direction: negative
    once the sphere was pushed past the goal), ``final_error_um``, ``frames`` (frames to
    termination), ``correction_um`` (δ or Δ at the end). With ``keep_paths`` also ``t``,
    ``robot_xy``, ``robot_heading``, ``spheres_xy``.
    """
    trials = list(trials)
    batch = len(trials)
    diagram = push_loop(exp)
    task = diagram.blocks["controller"].blocks["task"]
    g = geometry(exp.kind)
    radius = sphere_params().radius
    max_att = int(task.max_attempts)
    target = getattr(task, "target", None)   # a planned assembly: its arrangement's RMS bond error
    goal = g["spheres"][-1] if g["goal"] is None else g["goal"]

    def error_of(spheres):
        return target.error(spheres) if target is not None else task_error(exp.kind, spheres, g["goal"], radius)

    errors = np.full((batch, max_att + 1), np.nan)
    errors[:, 0] = error_of(g["spheres"][None])
    # signed: along the first sphere's line to its goal (a planned assembly has none: its bond error again)
    along = goal - g["spheres"][0]
    along = along / np.linalg.norm(along)
    signed = np.full((batch, max_att + 1), np.nan)
    signed[:, 0] = errors[:, 0] if target is not None else (goal - g["spheres"][0]) @ along
    status = np.full(batch, Status.RUNNING, dtype=np.int64)
    attempts = np.zeros(batch, dtype=np.int64)
    frames = np.full(batch, exp.max_frames, dtype=np.int64)
    correction = np.zeros(batch)
    paths: dict[str, list] = {k: [] for k in RECORD}
    state = None
    done_frames = 0
    while done_frames < exp.max_frames:
        steps = min(chunk_frames, exp.max_frames - done_frames)
        res = simulate(diagram, steps, batch=batch, seed=seed, trials=trials, record=RECORD, state=state,
                       engine=study_engine())
        state = res.final_state
        st, att = res[STATUS], res[ATTEMPT]
        err = error_of(res[SPHERES])
        prev = np.concatenate([attempts[:, None], att[:, :-1]], axis=1)
        bumped = att > prev
        rows, cols = np.nonzero(bumped)
        slot = np.minimum(att[rows, cols], max_att)
        errors[rows, slot] = err[rows, cols]
        signed[rows, slot] = (err[rows, cols] if target is not None
                              else np.einsum("ki,i->k", goal - res[SPHERES][rows, cols, 0], along))
        ended = (st != Status.RUNNING) & (status == Status.RUNNING)[:, None]
        first_end = np.where(ended.any(axis=1), ended.argmax(axis=1), -1)
        newly = first_end >= 0
        frames[newly] = done_frames + first_end[newly]
        status, attempts = st[:, -1].copy(), att[:, -1].copy()
        correction = res[CORRECTION][:, -1].copy()
        if keep_paths:
            for k in RECORD:
                paths[k].append(res[k])
        done_frames += steps
        if not (status == Status.RUNNING).any():
            break
    final = error_of(res[SPHERES][:, -1][:, None])[:, 0]
    out = {
        "status": status, "attempts": attempts, "error_um": errors / UM, "signed_error_um": signed / UM,
        "final_error_um": final / UM,
        "frames": frames, "correction_um": correction / UM,
    }
    if keep_paths:
        cat = {k: np.concatenate(v, axis=1) for k, v in paths.items()}
        out.update(t=np.arange(cat[ROBOT].shape[1]) * diagram.dt, robot_xy=cat[ROBOT],
                   robot_heading=cat[HEADING], spheres_xy=cat[SPHERES])
    return out
