"""D_p,r as the front-push task performs it, and the face–sphere contact gap calibrated there.

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
the frame the task measures (end of ``SETTLE``). The sphere follows the robot through the squeeze
film between the robot's face and the sphere (:mod:`magctl.plant.fluid.lubrication`), by
``(A/aζ*) ln(h_c/h_min)``: the one parameter of the plant the paper does not give is the gap
``h_min`` at which that film ends in rough contact. :func:`calibrate_in_task` fits it so that the
mean pull-back equals the measured 300 µm (Pchip in log h_min through a geometric grid, then
brentq), with the sphere–glass gap at the measured ε = 25 nm. ``models/sphere.toml``
``[contact] robot_gap_um`` holds the result; a test recomputes it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import PchipInterpolator
from scipy.optimize import brentq

from magctl.control.push.front import PUSH, RETRACT
from magctl.core import simulate
from magctl.loops import Experiment, Variability, geometry, push_loop
from magctl.plant.fluid.calibration import PAPER_RELEASE_EXPERIMENT
from magctl.studies.trials import study_engine

PHASE, ATTEMPT = "controller/task.phase", "controller/task.attempt"
SPHERES, ROBOT = "plant/spheres.spheres", "plant/robot.position"
FIRST_ATTEMPT_FRAMES = 400
"""Frames that hold the first attempt of the default front push (approach, push, retract, settle ≈ 160)."""
GAP_GRID = tuple(float(e) for e in np.geomspace(25e-9, 30e-6, 7))
"""h_min grid of the calibration [m]: the sphere's measured 25 nm roughness up to 30 µm."""


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
    """

    pull_back: np.ndarray
    overshoot: np.ndarray
    stop_gap: np.ndarray
    retract: np.ndarray


def release_experiment(contact_gap: float | None, *, scatter: float = 0.0) -> Experiment:
    """The front push whose first attempt is measured: the study's plant (camera noise and
    stick-slip variability on) with face–sphere contact gap ``contact_gap`` (``None``: the model's)."""
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
                   record=[PHASE, ATTEMPT, SPHERES, ROBOT])
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
    return InTaskRelease(pull, over, stop, back)


def calibrate_in_task(target: float = PAPER_RELEASE_EXPERIMENT, *, trials: int = 16, seed: int = 0,
                      grid: tuple[float, ...] = GAP_GRID, refine: int = 2) -> dict:
    """``h_min`` for which the mean in-task pull-back equals ``target`` [m].

    A Pchip interpolant of log(mean pull-back) in log h_min through ``grid`` brackets the root
    (brentq); ``refine`` Newton steps on the simulated response then remove the interpolation error.

    Returns ``contact_gap`` (h_min, m), ``grid`` and ``grid_release`` (mean pull-back at each h_min, m),
    ``model`` (mean, std at the value of ``models/sphere.toml``) and ``calibrated`` (mean, std at the
    fitted value), all in metres.
    """
    means = np.array([in_task_release(h, trials=trials, seed=seed).pull_back.mean() for h in grid])
    if not np.all(np.diff(means) < 0):
        raise RuntimeError(f"in-task release is not decreasing in h_min on the grid: {np.round(means * 1e6, 1)} µm")
    lh = np.log(grid)
    f = PchipInterpolator(lh, np.log(means))
    if not f(lh[-1]) <= np.log(target) <= f(lh[0]):
        raise RuntimeError(f"target {target * 1e6:.0f} µm outside the grid's {means[-1] * 1e6:.0f}–"
                           f"{means[0] * 1e6:.0f} µm")
    x = brentq(lambda x: f(x) - np.log(target), lh[0], lh[-1], xtol=1e-6)
    slope = float(f.derivative()(x))
    for _ in range(refine):  # Newton steps on the simulated response, with the interpolant's slope
        cal = in_task_release(float(np.exp(x)), trials=trials, seed=seed).pull_back
        x += (np.log(target) - np.log(cal.mean())) / slope
    gap = float(np.exp(x))
    now = in_task_release(None, trials=trials, seed=seed).pull_back
    cal = in_task_release(gap, trials=trials, seed=seed).pull_back
    return {"contact_gap": gap, "grid": np.asarray(grid), "grid_release": means,
            "model": (float(now.mean()), float(now.std())), "calibrated": (float(cal.mean()), float(cal.std()))}
