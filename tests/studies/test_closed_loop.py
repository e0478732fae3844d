"""The closed-loop push experiments: batch independence and the paper's headline claims.

Monte Carlo tolerances: a handful of seeded trials per controller, with claims loose
enough to hold for any seed yet able to fail if the mechanism behind them breaks.
"""

import numpy as np
import pytest

from magctl.control.push_params import task_defaults
from magctl.control.status import Status
from magctl.core.units import UM
from magctl.loops import Experiment, Variability, experiment_controller
from magctl.studies.trials import run_push_trials

CONVERGED, ATTEMPT_LIMIT = Status.CONVERGED, Status.ATTEMPT_LIMIT

TRIALS = 8


def test_a_trial_does_not_depend_on_its_batch():
    exp = Experiment("front", task=dict(kc=1.0, delta0=100 * UM, max_attempts=2), max_frames=450,
                     variability=Variability())
    together = run_push_trials([2, 5, 7], 11, exp=exp, keep_paths=True)
    alone = run_push_trials([5], 11, exp=exp, keep_paths=True)
    n = alone["spheres_xy"].shape[1]          # alone, the run stops when trial 5 has; together, with the last
    assert n > 100 and together["spheres_xy"].shape[1] >= n
    assert np.array_equal(together["spheres_xy"][1, :n], alone["spheres_xy"][0])
    assert np.array_equal(together["robot_xy"][1, :n], alone["robot_xy"][0])
    assert not np.array_equal(together["robot_xy"][0], together["robot_xy"][1])  # trials do differ


@pytest.fixture(scope="module")
def front_runs():
    plant = Variability(release_scatter=0.1)
    runs = {}
    for label, kc, d0 in (("naive", 0.0, 0.0), ("kc1_model", 1.0, 100 * UM)):
        exp = Experiment("front", task=dict(kc=kc, delta0=d0, max_attempts=6), max_frames=2600, variability=plant)
        runs[label] = run_push_trials(range(TRIALS), 0, exp=exp)
    return runs


def test_naive_front_push_keeps_a_steady_error_of_the_release_order(front_runs):
    """K_c = 0, δ(0) = 0 (§VI-A): the release displacement leaves the sphere short of the goal in the trials that
    use every attempt (on the one plant the in-task release is ≈ 135 µm, so a share of the naive pushes lands
    within ε_p by chance: the front-push study reports it)."""
    r = front_runs["naive"]
    stuck = r["status"] == ATTEMPT_LIMIT
    assert stuck.any()
    steady = np.median(r["final_error_um"][stuck])
    assert 75 < steady < 400  # paper: about 200 µm (300 µm release minus ~100 µm servo overshoot)


def test_learning_front_push_converges(front_runs):
    r = front_runs["kc1_model"]
    assert (r["status"] == CONVERGED).mean() >= 0.75
    assert (r["status"] == CONVERGED).mean() > (front_runs["naive"]["status"] == CONVERGED).mean()


@pytest.fixture(scope="module")
def side_runs():
    plant = Variability(release_scatter=0.0)
    runs = {}
    for label, kw in (("fixed370", dict(fixed_gap=370 * UM, ks=0.0)), ("learn", dict(model="lin", ks=0.9))):
        exp = Experiment("side", task=dict(kw, max_attempts=14), max_frames=6500, variability=plant)
        runs[label] = run_push_trials(range(4), 0, exp=exp)
    return runs


def test_side_push_with_learning_reaches_one_pixel(side_runs):
    r = side_runs["learn"]
    assert (r["status"] == CONVERGED).mean() >= 0.75
    done = r["status"] == CONVERGED
    assert (r["final_error_um"][done] < 7.5 + 7.5).all()  # ε_p on the tracker's estimate; one more pixel of truth


def test_learning_beats_the_fixed_small_gap(side_runs):
    """D_g = 370 µm fixed (§VI-B) over-pushes once the sphere is close, so it converges only by chance."""
    fixed, learn = side_runs["fixed370"], side_runs["learn"]
    assert (learn["status"] == CONVERGED).mean() > (fixed["status"] == CONVERGED).mean()
    assert np.mean(learn["attempts"]) < np.mean(fixed["attempts"])


def test_side_push_study_repositions_where_the_sphere_is_not_disturbed():
    """§VI repositions at ≥ 650 µm because eq 22 predicts only ≈ 4.9 µm of drift there. The side-push
    clearance of the controller every study and the rig run (models/push.toml) must meet the paper's criterion
    on the plant in use; in the default oil layer the drift at 650 µm is eq 22's within 15 %."""
    from analysis import side_push
    from magctl.plant.fluid.scenarios import sidepush_curve

    paper_drift_650 = 1755.0 * np.exp(-0.009042 * 650.0)  # eq 22, µm
    clearance = task_defaults("side")["clearance"]
    ours = sidepush_curve([650 * UM, clearance]).displacement / UM
    assert ours[0] == pytest.approx(paper_drift_650, rel=0.15)
    assert ours[1] <= paper_drift_650
    assert all(experiment_controller(e).blocks["task"].clearance == clearance
               for e in side_push.experiments().values())
