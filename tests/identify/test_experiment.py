"""The identification experiment: its plan (gaps above the side push's contact bound, a geometry that stays in the
camera field) and its runner (one log per run through the rig runtime, the expected ends, a clear stop on a fault).
Expected values come from ``models/identify.toml`` ``[experiment]``, ``models/push.toml`` and the task registry."""

import math

import numpy as np
import pytest

from magctl.config import load_file, load_model, models_dir
from magctl.control.status import Status
from magctl.identify.experiment import (
    ExperimentError,
    RunSpec,
    goal_towards_centre,
    log_name,
    plan,
    run_experiment,
)
from magctl.rig.log import read_log
from magctl.rig.tasks import IDENTIFY_OUTCOMES, PUSH_OUTCOMES, check_options
from magctl.sensing.camera import field_of_view, outside_view

E = load_model("identify").experiment
COMMON = load_model("push").common   # the field margin the sweep keeps
PUSH = load_model("push")
SCENE = load_model("rig").scene
W, H = field_of_view()
STOPS = {"converged": PUSH_OUTCOMES[Status.CONVERGED], "attempt_limit": PUSH_OUTCOMES[Status.ATTEMPT_LIMIT]}


def _inside(points, margin=0.0):
    p = np.asarray(points, dtype=float)
    return ~outside_view(p - margin, (W - 2 * margin, H - 2 * margin))


def test_the_plan_runs_the_sweep_the_front_pushes_and_a_gap_ladder_above_the_contact_bound():
    specs = plan()
    assert [s.task for s in specs] == (["identify"] + ["front-push"] * len(E.front_goals)
                                       + ["side-push"] * len(E.side_gaps))
    assert len({s.name for s in specs}) == len(specs)
    for s in specs:
        check_options(s.task, s.options)
    sides = [s for s in specs if s.task == "side-push"]
    gaps = [s.options["fixed_gap_um"] * 1e-6 for s in sides]
    np.testing.assert_allclose(gaps, E.side_gaps)
    assert min(gaps) >= PUSH.side.min_gap
    assert all(s.options["max_attempts"] == int(E.passes_per_gap) for s in sides)
    assert all(set(s.ends) == {"converged", "attempt_limit"} for s in sides)
    fronts = [s for s in specs if s.task == "front-push"]
    np.testing.assert_allclose([s.push_length for s in fronts], E.front_goals)
    assert all(s.options["max_attempts"] == int(E.front_attempts) for s in fronts)


def test_a_gap_below_the_contact_bound_is_refused(tmp_path):
    src = (models_dir() / "identify.toml").read_text("utf-8")
    low = PUSH.side.min_gap * 1e6 - 1.0
    assert src.count("side_gaps_um = { value = [") == 1
    (tmp_path / "identify.toml").write_text(src.replace("side_gaps_um = { value = [",
                                                        f"side_gaps_um = {{ value = [{low}, "), "utf-8")
    with pytest.raises(ExperimentError, match="min_gap"):
        plan(load_file(tmp_path / "identify.toml"))


def test_the_plans_geometry_stays_in_the_camera_field_from_the_default_scene():
    """The front pushes' goals and approach points, then the side passes round where they leave the sphere, each
    as planned from the default scene (every push reaching its goal)."""
    sphere = np.asarray(SCENE.robot_start, dtype=float) + np.array([SCENE.sphere_spacing, 0.0])
    margin = COMMON.field_margin
    for s in plan():
        if s.push_length is None:
            continue
        goal = goal_towards_centre(sphere, s.push_length)
        away = (goal - sphere) / np.hypot(*(goal - sphere))
        approach = sphere - PUSH.front.approach * away
        assert _inside([goal, approach], margin).all(), s.name
        sphere = goal
    # a side pass runs from `behind` before the sphere to `ahead` past it at its gap, in any direction
    reach = math.hypot(max(PUSH.side.behind, PUSH.side.ahead), max(E.side_gaps))
    ring = sphere + reach * np.stack([np.cos(a := np.linspace(0, 2 * np.pi, 73)), np.sin(a)], axis=1)
    assert _inside(ring, margin).all()


@pytest.fixture(scope="module")
def standin_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("experiment")
    calls = []
    paths = run_experiment("sim", out, plant="standin", progress=lambda *a: calls.append(a))
    return out, paths, calls


def test_the_whole_plan_on_the_standin_rig_writes_one_log_per_run_with_the_expected_end(standin_run):
    out, paths, calls = standin_run
    specs = plan()
    assert paths == [out / log_name(i, s) for i, s in enumerate(specs, 1)]
    assert [(c[0], c[1], c[2].name, c[3] is None) for c in calls] == [
        (i, len(specs), s.name, before) for i, s in enumerate(specs, 1) for before in (True, False)]
    spheres = None
    for spec, path in zip(specs, paths, strict=True):
        log = read_log(path)
        assert log.stop is not None and log.start["task"] == spec.task
        if spec.task == "identify":
            assert (log.stop["exit_status"], log.stop["reason"]) == IDENTIFY_OUTCOMES[Status.CONVERGED]
        else:
            assert (log.stop["exit_status"], log.stop["reason"]) in [STOPS[e] for e in spec.ends]
        if spec.push_length is not None:  # aimed from where the previous run left the sphere
            want = goal_towards_centre(spheres, spec.push_length)
            np.testing.assert_allclose(log.start["options"]["goal_m"], want, atol=1e-9)
        robot = np.array([e["obs"]["robot_est_m"] for e in log.events])
        sph = np.array([e["obs"]["spheres_est_m"] for e in log.events]).reshape(-1, 2)
        assert not any(e["obs"]["lost"] for e in log.events)
        assert _inside(robot).all() and _inside(sph).all(), path.name
        spheres = sph[-1]


def test_one_sweep_on_the_physical_rig_ends_done_with_the_robot_back_near_its_start(tmp_path):
    (path,) = run_experiment("sim", tmp_path, plant="physics", specs=[RunSpec("sweep", "identify")])
    log = read_log(path)
    assert (log.stop["exit_status"], log.stop["reason"]) == IDENTIFY_OUTCOMES[Status.CONVERGED]
    robot = np.array([e["obs"]["robot_est_m"] for e in log.events])
    assert np.hypot(*(robot[-1] - robot[0])) <= E.side_max
    assert _inside(robot, COMMON.field_margin).all()
    segments = {int(e["outputs"]["segment"]) for e in log.events} - {-1}
    assert segments and segments == set(range(max(segments) + 1))


def test_a_run_ending_in_a_fault_stops_the_experiment_in_one_line(tmp_path):
    specs = [RunSpec("big", "identify", {"side_max_um": 3000.0}), RunSpec("never", "identify")]
    with pytest.raises(ExperimentError) as err:
        run_experiment("sim", tmp_path, plant="standin", specs=specs)
    msg = str(err.value)
    assert "\n" not in msg and log_name(1, specs[0]) in msg and "failed" in msg
    assert read_log(tmp_path / log_name(1, specs[0])).stop["exit_status"] == "failed"
    assert not (tmp_path / log_name(2, specs[1])).exists()


def test_existing_logs_and_bad_options_are_refused_before_the_rig_is_touched(tmp_path):
    specs = [RunSpec("sweep", "identify")]
    (tmp_path / log_name(1, specs[0])).write_text("x")
    with pytest.raises(ExperimentError, match="never overwritten"):
        run_experiment("tcp://127.0.0.1:1", tmp_path, specs=specs)
    with pytest.raises(ExperimentError, match="hold"):
        run_experiment("tcp://127.0.0.1:1", tmp_path / "new", specs=[RunSpec("sweep", "identify", {"hold_s": -1})])
    with pytest.raises(ExperimentError, match="needs a run before it"):
        run_experiment("tcp://127.0.0.1:1", tmp_path / "new", specs=[RunSpec("p", "front-push", push_length=5e-4)])
    assert not (tmp_path / "new").exists()
