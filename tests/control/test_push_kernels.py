"""The controller's kernels against their numpy references (``tests/reference``) on closed push loops.

* **controller only** — every push task with the PI servo behind it (the controller's blocks), fed the
  tracker outputs an interpreted run of the closed stand-in loop recorded: the task's numpy reference and the
  compiled kernels must give the same outputs at every frame and the same final state (1e-12 relative,
  integers exactly), through approaches, pushes, passes, settles, law updates and the front-then-side
  hand-over;
* **closed loops** — the rig's loop and the ideal loop of ``test_push`` run by both engines (``"auto"``
  compiles what has kernels); and ``magctl.loops.controller`` of every push task compiles when its
  blocks have kernels.
"""

import dataclasses

import numpy as np
import pytest
from reference import reference_of
from test_push import EXACT, ideal_loop, rig_loop

from magctl.control.learning import front_push_law
from magctl.control.phases import FINISHED, FRONT_PHASE_OFFSET, SidePhase
from magctl.control.push.assembly import AssemblyTask, FrontAssemblyTask, FrontThenSideAssemblyTask
from magctl.control.push.front import FrontPushTask
from magctl.control.push.side import SidePushTask
from magctl.control.servo import Servo
from magctl.control.side_models import TabulatedSideModel, side_model
from magctl.core.block import STREAM, flat_state_vars, state_get
from magctl.core.diagram import Diagram
from magctl.core.simulation import simulate
from magctl.core.units import UM
from magctl.loops import PUSH_TASKS, controller

RTOL = 1e-12
ATOL = 1e-15
"""Metres: 1e-12 of the millimetre workspace. ``around``'s waypoint ``o + 1.08·c·sin(a)`` can cancel to ~1e-19 m,
where the last bit of numpy's vectorised ``arctan2`` (SVML on AVX-512, 1 ulp from libm's ``math.atan2`` in ~8 %
of arguments) makes the relative error large; a closed-loop difference is that small in absolute terms."""
ONE = [[0.0, 0.0]]
PAIR = [[0.0, 0.0], [800 * UM, 0.0]]


def _curve_task(**kw):
    """The curve-learning side push (prior exp-fit), every pass a measured one: goal 300 µm, clearance as the
    other side-push cases."""
    return SidePushTask(goal=(300 * UM, 0.0), learning="curve", model="exp-fit", clearance=850 * UM, **(EXACT | kw))


def _table_model():
    m = side_model("exp")
    gaps = np.linspace(300 * UM, 900 * UM, 7)
    return TabulatedSideModel(tuple(gaps), tuple(m.displacement(gaps) * (1 + 0.1 * np.sin(gaps / UM / 97))))


CASES = {
    "front-push": lambda: (FrontPushTask(goal=(750 * UM, 0.0), kc=0.5, delta0=127 * UM, **EXACT), ONE, 900),
    "front-push, one K_c per trial": lambda: (FrontPushTask(goal=(750 * UM, 0.0), law=front_push_law([0.3, 0.7, 1.2],
                                                                                                   60 * UM),
                                                        **EXACT), ONE, 900),
    "front-assemble": lambda: (FrontAssemblyTask(kc=1.0, max_attempts=3, eps_as=10 * UM, **EXACT), PAIR, 900),
    "side-push lin": lambda: (SidePushTask(goal=(300 * UM, 0.0), ks=0.9, model="lin", clearance=850 * UM,
                                           **EXACT), ONE, 900),
    "side-push exp": lambda: (SidePushTask(goal=(300 * UM, 0.0), ks=0.5, model="exp", clearance=850 * UM,
                                           **EXACT), ONE, 900),
    "side-push lin-fit": lambda: (SidePushTask(goal=(300 * UM, 0.0), ks=0.9, model="lin-fit", clearance=850 * UM,
                                               **EXACT), ONE, 900),
    "side-push table": lambda: (SidePushTask(goal=(300 * UM, 0.0), ks=0.7, model=_table_model(),
                                             clearance=850 * UM, **EXACT), ONE, 900),
    "side-push fixed gap": lambda: (SidePushTask(goal=(300 * UM, 0.0), fixed_gap=500 * UM, clearance=850 * UM,
                                                 max_attempts=4, **EXACT), ONE, 900),
    "assemble": lambda: (AssemblyTask(ks=0.9, model="lin", clearance=850 * UM, eps_as=10 * UM, **EXACT),
                         [[0.0, 0.0], [500 * UM, 0.0]], 900),
    "front-side-assemble": lambda: (FrontThenSideAssemblyTask(front_attempts=1, ks=0.9, model="lin",
                                                              clearance=850 * UM, eps_as=10 * UM, **EXACT),
                                    PAIR, 1500),
    # the laws beyond the paper (docs/push-control.md §6, §7): the curve-learning side push with its push-out turn,
    # its front push answering dirt, the release-model front push; the curve law in the assemblies
    "side-push curve": lambda: (_curve_task(), ONE, 1500),
    "side-push curve, fixed gap": lambda: (_curve_task(fixed_gap=450 * UM, max_attempts=4), ONE, 900),
    "side-push curve, front push on dirt": lambda: (_curve_task(dirt_response="front"), ONE, 2400),
    "side-push curve, front push first": lambda: (_curve_task(dirt_response="front-first"), ONE, 2400),
    "front-push release model": lambda: (FrontPushTask(goal=(750 * UM, 0.0), learning="release", **EXACT), ONE, 900),
    "assemble curve": lambda: (AssemblyTask(learning="curve", model="exp-fit", clearance=850 * UM, eps_as=10 * UM,
                                            **EXACT), [[0.0, 0.0], [500 * UM, 0.0]], 1500),
    "front-side-assemble curve": lambda: (FrontThenSideAssemblyTask(front_attempts=1, learning="curve",
                                                                    model="exp-fit", clearance=850 * UM,
                                                                    eps_as=10 * UM, **EXACT), PAIR, 1500),
}
ROBOT0 = {"assemble": (-1e-3, 300 * UM), "assemble curve": (-1e-3, 300 * UM)}
LOOP = {"side-push curve, front push on dirt": {"side_scale": [0.15, 1.0, 0.3]}}
"""Options of the stand-in loop: spheres at 15 % and 30 % of eq 22's mobility (read as stuck), one as the prior."""


def _assert_paths_taken(case, task, phase, final):
    """The recorded run went where the case is for: the curve law learned a push-out, the release law chose on
    its map, the dirt answered with a front push (its phases offset) in the stuck trials only."""
    law = final["law"] if "law" in final else final.get("side", {}).get("law", {})
    if "curve" in case and "fixed gap" not in case:
        po = final["push_out_n"] if "push_out_n" in final else final["side"]["push_out_n"]
        assert po.max() >= 1
        assert np.any(law["theta"] != task_law(task).prior_mean)
    if "release" in case:
        assert (law["neighbours"] >= 0).all(axis=1).any()
    if "dirt" in case:
        fronting = (phase > FRONT_PHASE_OFFSET) & (phase < FINISHED)
        assert list(fronting.any(axis=1)) == list(final["fronts"] > 0) == [True, False, True]
    if "front push first" in case:   # every trial starts with the coarse front push, then passes
        fronting = (phase > FRONT_PHASE_OFFSET) & (phase < FINISHED)
        assert fronting[:, :5].any(axis=1).all() and (final["fronts"] >= 1).all()
        passing = phase == int(SidePhase.PASS)                # side passes follow the front push
        assert passing.any(axis=1).all() and (fronting.argmax(axis=1) < passing.argmax(axis=1)).all()


def task_law(task):
    return task.side.law if hasattr(task, "side") else task.law


def assert_same(a, b, where):
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape, where
    if a.dtype.kind == "f":
        np.testing.assert_allclose(b, a, rtol=RTOL, atol=ATOL, equal_nan=True, err_msg=where)
    else:
        assert np.array_equal(a, b), where


def controller_only(task) -> Diagram:
    """``task`` → PI servo (the rig's controller without the drive), inputs as the tracker gives them."""
    servo = Servo("servo", speed_cap_input=True, hold_input=True)
    n = task.name
    return Diagram("ctrl", [task, servo], [(f"{n}.target", "servo.target"), (f"{n}.speed_cap", "servo.speed_cap")],
                   inputs={"robot_est": [f"{n}.robot_est", "servo.robot_est"], "spheres_est": [f"{n}.spheres_est"],
                           "lost": [f"{n}.lost", "servo.hold"]},
                   outputs={**{p: f"{n}.{p}" for p in task.outputs}, "speed": "servo.speed",
                            "heading": "servo.heading"})


@pytest.mark.parametrize("case", sorted(CASES))
def test_controller_kernels_match_on_recorded_tracker_outputs(case):
    task, spheres, steps = CASES[case]()
    assert task.kernel() is not None
    loop = ideal_loop(task, ROBOT0.get(case, (-1e-3, 0.0)), spheres, blackout=(200.5 / 30, 215.5 / 30),
                      **LOOP.get(case, {}))
    rec = ["tracker.robot_est", "tracker.spheres_est", "tracker.lost", f"{task.name}.attempt", f"{task.name}.status",
           f"{task.name}.phase"]
    run = simulate(loop, steps, batch=3, seed=5, record=rec, check_finite=False)
    assert run[rec[3]][:, -1].max() >= 1  # attempts were made
    final = next(st for lf, st in zip(loop.schedule.leaves, run.final_state["leaves"], strict=True)
                 if lf.path == task.name)
    _assert_paths_taken(case, task, run[rec[5]], final)
    inputs = {p: run[f"tracker.{p}"] for p in ("robot_est", "spheres_est", "lost")}
    d = controller_only(task)
    ref = simulate(controller_only(reference_of(task)), steps, batch=3, seed=5, inputs=inputs, check_finite=False)
    got = simulate(d, steps, batch=3, seed=5, inputs=inputs, check_finite=False, engine="compiled")
    assert_same(ref[f"{task.name}.status"], run[f"{task.name}.status"], "replay")
    # a commanded heading is the angle of the vector to the target; where the servo commands no speed that vector
    # cancels to ~1e-19 m and its angle is a last-bit sign (as in test_ideal_loop_engines_agree): compared where
    # either engine commands the robot to move
    moving = (ref["speed"] > 1e-9) | (got["speed"] > 1e-9)
    for name in d.outputs:
        if name == "heading":
            assert_same(np.where(moving, ref[name], 0.0), np.where(moving, got[name], 0.0), f"{case}: {name}")
        else:
            assert_same(ref[name], got[name], f"{case}: {name}")
    for i, block in enumerate((task, d.blocks["servo"])):
        for keys, var in flat_state_vars(block.state_vars()):
            if var.dtype != STREAM:
                a, b = (state_get(r.final_state["leaves"][i], keys) for r in (ref, got))
                assert_same(a, b, f"{case}: final {'.'.join(keys)}")


@pytest.mark.parametrize("task,options", [("front-push", {"kc": 0.5, "delta0": 127 * UM}),
                                          ("front-push", {"learning": "release"}),
                                          ("side-push", {"ks": 0.9, "model": "lin"}),
                                          ("side-push", {"ks": 0.5, "model": "exp"}),
                                          ("side-push", {"ks": 0.9, "model": "lin-fit"}),
                                          ("side-push", {"learning": "curve", "model": "exp-fit"})])
def test_rig_loop_engines_agree(task, options):
    dia, _ = rig_loop(task, **options)
    rec = ["controller/task.status", "controller/task.attempt", "controller/task.phase",
           "controller/task.correction", "controller/task.target", "controller/servo.speed", "plant/robot.position"]
    ref = simulate(dia, 400, batch=2, seed=3, record=rec)
    got = simulate(dia, 400, batch=2, seed=3, record=rec, engine="auto")
    for k in rec:
        assert_same(ref[k], got[k], k)


@pytest.mark.parametrize("case", ["assemble", "front-side-assemble"])
def test_ideal_loop_engines_agree(case):
    task, spheres, steps = CASES[case]()
    loop = ideal_loop(task, ROBOT0.get(case, (-1e-3, 0.0)), spheres)
    ref = simulate(loop, steps, batch=2, seed=3)
    got = simulate(loop, steps, batch=2, seed=3, engine="compiled")
    moving = ref["servo.speed"] > 1e-9         # m/s: a step of more than 3e-11 m
    for _lag in range(2):   # the robot's heading lags the command a frame, the tracker's two
        moving = moving & np.concatenate([np.zeros_like(moving[:, :1]), moving[:, :-1]], axis=1)
    for k in ref.signals:
        if k.split(".")[-1].startswith("heading"):
            # on its target the heading is the angle of a vanishing vector (a difference that cancels to
            # ~1e-19 m), ±π/2 by a last-bit sign: compared where the robot really moves
            assert_same(np.where(moving, ref[k], 0.0), np.where(moving, got[k], 0.0), k)
        else:
            assert_same(ref[k], got[k], k)


CURVE = {"learning": "curve", "model": "exp-fit"}
RIG_OPTIONS = [(task, {}) for task in sorted(PUSH_TASKS)] + [
    ("front-push", {"learning": "release"}), ("side-push", CURVE), ("side-push", CURVE | {"dirt_response": "front"}),
    ("side-push", CURVE | {"fixed_gap": 450 * UM}), ("assemble", CURVE), ("front-side-assemble", CURVE)]
"""The push controllers the rig builds (``magctl.rig.tasks``: every task, the learning laws and the answer to
dirt its options select)."""


@pytest.mark.parametrize("task,options", RIG_OPTIONS, ids=[f"{t} {o}" for t, o in RIG_OPTIONS])
def test_the_push_controllers_compile(task, options):
    goal = (750 * UM, 0.0) if task in ("front-push", "side-push") else None
    d = controller(task, n_spheres=2 if goal is None else 1, goal=goal, **options)
    assert d.blocks["task"].kernel() is not None and d.blocks["servo"].kernel() is not None
    assert d.compile().source  # task, servo and drive compile


# --- the studies' closed loops -------------------------------------------------------------------------
def study_experiments() -> dict:
    """Every push experiment the studies run, by label: analysis/front_push.py, side_push.py, robustness.py,
    side_push_mismatch.py, assembly.py, beyond.py and the release studies of magctl.studies."""
    from magctl.studies import runner as studies
    from magctl.studies.front_release import identification_experiments
    from magctl.studies.release_calibration import release_experiment

    front, side, assembly, beyond = (studies.get(n) for n in ("front-push", "side-push", "assembly", "beyond"))
    robust, mismatch = studies.get("robustness"), studies.get("side-push-mismatch")
    dirty = dataclasses.replace(side.PLANT, sticky_probability=robust.STICKY)
    exps = {**front.controllers(front.model_delta0()), **front.controllers(0.0), **side.experiments(),
            **assembly.experiments(), **beyond.experiments(), **beyond.front_experiments(),
            **beyond.assembly_experiments(), **identification_experiments(),
            "release in task": release_experiment(None)}
    exps |= {f"{label}, dirt": side.side_experiment(f"{label}, dirt", side.CONTROLLERS[label], dirty)
             for label in robust.LAWS}
    exps |= {label: side.side_experiment(label, {"model": model, "ks": ks})
             for label, (model, ks, _twin) in mismatch.PAIRS.items()}
    return exps


def test_auto_compiles_every_study_loop():
    """``engine="auto"`` (the studies' engine) runs every study's closed loop compiled — the curve-learning side
    push, its answer to dirt, the release-model front push and the planned assemblies, whose pass planner (casadi,
    IPOPT) is a Python event of the compiled frame."""
    from magctl.loops import push_loop

    exps = study_experiments()
    planned = []
    for label, exp in exps.items():
        d = push_loop(exp)
        assert all(lf.block.kernel() is not None for lf in d.schedule.leaves), label
        compiled = d.compile()
        assert compiled.source, label
        if compiled.events:
            planned.append(label)
    assert {"curve learning (exp-fit prior)", "curve learning + front push on dirt, dirt",
            "release-model controller"} <= set(exps) - set(planned)
    assert planned and all("planned" in label or "greedy" in label for label in planned), planned


def _study_loop(label, sticky=None):
    from magctl.loops import push_loop

    exps = study_experiments()
    exp = exps[label]
    if sticky is not None:   # every sphere on a sticky patch: the curve law reads it as stuck
        exp = dataclasses.replace(exp, variability=dataclasses.replace(exp.variability, sticky_probability=sticky))
        # at the paper's 370 µm bound a stuck sphere needs more passes than [dirt] allows, so the front push runs
        exp = dataclasses.replace(exp, task=exp.task | {"min_gap": 370 * UM})
    return push_loop(exp)


STUDY_LOOPS = {
    "curve law, push-out turn": ("curve learning (exp-fit prior)", None, 3, 2400),
    "curve law, front push on dirt": ("curve learning + front push on dirt, dirt", 1.0, 2, 1500),
    "release-model front push": ("release-model controller", None, 6, 1500),
}


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(STUDY_LOOPS))
def test_study_loops_engines_agree(name):
    """The studies' loops beyond the paper (analysis/beyond.py on the physical plant) by both engines, same seed:
    the same status, attempts and phases at every frame, the same corrections, targets and robot path (1e-12)."""
    label, sticky, batch, frames = STUDY_LOOPS[name]
    d = _study_loop(label, sticky)
    rec = ["controller/task.status", "controller/task.attempt", "controller/task.phase", "controller/task.correction",
           "controller/task.target", "plant/robot.position"]
    ref = simulate(d, frames, batch=batch, seed=2, record=rec, engine="interpreted")
    got = simulate(d, frames, batch=batch, seed=2, record=rec, engine="compiled")
    for k in rec:
        assert_same(ref[k], got[k], f"{name}: {k}")
    assert ref["controller/task.attempt"][:, -1].max() >= 2   # the law learned from a measured attempt
    if sticky:
        phase = ref["controller/task.phase"]
        assert ((phase > FRONT_PHASE_OFFSET) & (phase < FINISHED)).any(axis=1).all()   # each answered with a front push
