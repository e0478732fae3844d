"""D_p,r as the front-push task performs it.

The paper measured D_p,r ≈ 300 ± 75 µm (§IV-D) as the distance a pushed sphere follows
the robot when it backs away. The idealised scenario of
:func:`magctl.plant.fluid.scenarios.release_displacement` (the sphere resting in the
notch, the robot backing 1.5 mm at 0.4 mm/s from rest) is the paper's simulation set-up,
but it is not what the closed loop does: the front-push task (:mod:`magctl.control.push.front`)
drives the sphere at the push speed, stops by eq 11 (the sphere within the push tolerance
of ``P_o``) with the servo still settling, backs ``retract`` at the travel speed and waits
``settle_frames`` before it measures. Every one of those changes how far the sphere follows.

:func:`in_task_release` runs the first attempt of the closed-loop front push (the same
``loops.push_loop`` the studies and the rig use) and measures the pull-back: the sphere's
displacement against the push direction from the farthest point it reaches after the task
enters ``RETRACT`` (the servo's overshoot still pushes it on by contact for a few frames) to
the frame the task measures (end of ``SETTLE``). The sphere follows the robot through the robot's
flow and through the lubrication between the robot and the sphere
(:mod:`magctl.plant.fluid.lubrication`: at the notch the edge law, whose pull stays finite as the gap
``h₀`` the robot starts from closes); ``h_min``, the rough contact (``models/sphere.toml [contact]``), is
what :data:`GAP_GRID` scans. No parameter is fitted here: the plant is the one every study uses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magctl.control.push.front import PUSH, RETRACT
from magctl.core import simulate
from magctl.loops import Experiment, Variability, geometry, push_loop
from magctl.studies.trials import study_engine

PHASE, ATTEMPT = "controller/task.phase", "controller/task.attempt"
SPHERES, ROBOT, HEADING = "plant/spheres.spheres", "plant/robot.position", "plant/robot.heading"
FIRST_ATTEMPT_FRAMES = 400
"""Frames that hold the first attempt of the default front push (approach, push, retract, settle ≈ 160)."""
GAP_GRID = tuple(float(e) for e in np.geomspace(25e-9, 30e-6, 7))
"""h_min grid of the sensitivity scan [m]: the measured 25 nm roughness up to 30 µm."""


@dataclass(frozen=True)
class InTaskRelease:
    """The first attempt's release, per trial (metres).

    Attributes
    ----------
    pull_back : ndarray (B,)
        D_p,r in the task: the sphere's displacement against the push direction from the
        farthest point it reached after the push stopped to where it is measured.
    overshoot : ndarray (B,)
        How far the sphere went on along the push direction after the task entered
        ``RETRACT`` (the servo's overshoot still pushing it by contact).
    stop_gap : ndarray (B,)
        Robot centre to sphere centre when the push stopped (the task's contact state:
        the sphere sits in the notch at ``contact`` ≈ 250 µm).
    retract : ndarray (B,)
        How far the robot backed, push start of ``RETRACT`` to the measurement.
    turn : ndarray (B,)
        How far the robot's heading turned [rad] between the push's stop and the measurement (the
        stick-slip robot walks along its heading: backing away, it turns round).
    """

    pull_back: np.ndarray
    overshoot: np.ndarray
    stop_gap: np.ndarray
    retract: np.ndarray
    turn: np.ndarray


def release_experiment(contact_gap: float | None, *, scatter: float = 0.0) -> Experiment:
    """The front push whose first attempt is measured: the study's plant (camera noise and
    stick-slip variability on) with robot–sphere contact gap ``contact_gap`` (``None``: the model's)."""
    var = Variability(release_scatter=scatter, contact_gap=contact_gap)
    return Experiment("front", task=dict(kc=0.0, delta0=0.0), max_frames=FIRST_ATTEMPT_FRAMES, variability=var,
                      label="release in task")


def in_task_release(contact_gap: float | None = None, *, trials: int = 16, seed: int = 0,
                    scatter: float = 0.0) -> InTaskRelease:
    """Run the first attempt of ``trials`` closed-loop front pushes and measure the release.

    Raises
    ------
    RuntimeError
        If a trial does not finish its first attempt within :data:`FIRST_ATTEMPT_FRAMES`.
    """
    if trials < 1:
        raise ValueError(f"trials must be >= 1, got {trials}")
    exp = release_experiment(contact_gap, scatter=scatter)
    res = simulate(push_loop(exp), FIRST_ATTEMPT_FRAMES, batch=trials, seed=seed, engine=study_engine(),
                   record=[PHASE, ATTEMPT, SPHERES, ROBOT, HEADING])
    phase, attempt = res[PHASE], res[ATTEMPT]
    sphere, robot = res[SPHERES][:, :, 0], res[ROBOT]
    g = geometry("front")
    u = (g["goal"] - g["spheres"][0]) / np.linalg.norm(g["goal"] - g["spheres"][0])
    rows = np.arange(trials)
    entered = (phase == RETRACT) & np.concatenate([np.zeros((trials, 1), bool), phase[:, :-1] == PUSH], axis=1)
    measured = attempt >= 1
    if not (entered.any(axis=1) & measured.any(axis=1)).all():
        raise RuntimeError(f"a front push did not finish its first attempt in {FIRST_ATTEMPT_FRAMES} frames")
    k0, k1 = entered.argmax(axis=1), measured.argmax(axis=1)
    along = sphere @ u                                               # (B, T)
    frames = np.arange(along.shape[1])
    window = (frames >= k0[:, None]) & (frames <= k1[:, None])
    farthest = np.where(window, along, -np.inf).max(axis=1)
    pull = farthest - along[rows, k1]
    over = farthest - along[rows, k0]
    stop = np.linalg.norm(sphere[rows, k0] - robot[rows, k0], axis=-1)
    back = (robot[rows, k0] - robot[rows, k1]) @ u
    heading = res[HEADING]
    turn = np.abs(np.angle(np.exp(1j * (heading[rows, k1] - heading[rows, k0]))))
    return InTaskRelease(pull, over, stop, back, turn)
