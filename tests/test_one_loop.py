"""One closed loop: the controller a study runs is, block for block, the controller the rig runs.

The studies build their controller from an :class:`~magctl.loops.Experiment`; the rig builds it from
the first observation and the user's options through its task registry. Both must end in the same
function (:func:`magctl.loops.controller`) and in diagrams that are equal block for block: classes,
every parameter (recursively, arrays by value), ports and wiring.
"""

from __future__ import annotations

import dataclasses
import inspect

import numpy as np
import pytest
from scipy.spatial import cKDTree

import magctl.loops
import magctl.rig.tasks
from magctl.config import Params
from magctl.core.block import Block
from magctl.core.diagram import Diagram
from magctl.core.units import UM
from magctl.loops import Experiment, Variability, experiment_controller, geometry, push_loop
from magctl.rig.interface import Observation
from magctl.rig.tasks import build_task


def structure(obj, depth: int = 0):
    """A comparable description of a block or diagram: class, every attribute, ports, wiring."""
    if depth > 12:
        raise AssertionError("structure too deep (a cycle?)")
    if isinstance(obj, Diagram):
        return ("Diagram", obj.name, obj.dt,
                tuple((name, structure(b, depth + 1)) for name, b in obj.blocks.items()),
                tuple(sorted(obj.connections)), tuple(sorted((k, tuple(v)) for k, v in obj.exported_inputs.items())),
                tuple(sorted(obj.exported_outputs.items())))
    if isinstance(obj, Block):
        attrs = {k: v for k, v in vars(obj).items() if k not in ("inputs", "outputs")}
        return (type(obj).__qualname__, tuple(p.describe() for p in obj.inputs.values()),
                tuple(p.describe() for p in obj.outputs.values()), structure(attrs, depth + 1))
    if isinstance(obj, Params):
        return ("Params", structure(obj.to_dict(), depth + 1))
    if isinstance(obj, dict):
        return tuple(sorted((str(k), structure(v, depth + 1)) for k, v in obj.items()))
    if isinstance(obj, (list, tuple)):
        return tuple(structure(v, depth + 1) for v in obj)
    if isinstance(obj, np.ndarray):
        return ("array", obj.dtype.str, obj.shape, obj.tobytes())
    if isinstance(obj, cKDTree):  # a neighbour index is its points
        return ("cKDTree", structure(obj.data, depth + 1))
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return (type(obj).__qualname__, structure(vars(obj), depth + 1))
    if isinstance(obj, (int, float, str, bool, complex, type(None), np.generic)):
        return obj
    if callable(obj):
        return ("callable", getattr(obj, "__qualname__", repr(obj)))
    if hasattr(obj, "__dict__"):
        return (type(obj).__qualname__, structure(vars(obj), depth + 1))
    if hasattr(obj, "__slots__"):
        return (type(obj).__qualname__, structure({s: getattr(obj, s) for s in obj.__slots__}, depth + 1))
    return repr(obj)


def first_observation(kind: str) -> Observation:
    g = geometry(kind)
    return Observation(t=0.0, frame=0, robot_est=g["robot"].copy(), heading_est=0.0, spheres_est=g["spheres"].copy(),
                       lost=False)


# (study kind, rig task, options as a rig user types them, the same options as a study states them)
CASES = [
    ("front", "front-push", {}, {}),
    ("front", "front-push", {"kc": 0.5, "delta0_um": 127.0, "eps_um": 75.0, "max_attempts": 10},
     {"kc": 0.5, "delta0": 127 * UM, "eps": 75 * UM, "max_attempts": 10}),
    ("front", "front-push", {"learning": "release"}, {"learning": "release"}),
    ("side", "side-push", {}, {}),
    ("side", "side-push", {"model": "exp", "ks": 0.5, "clearance_mm": 1.0, "servo": "paper"},
     {"model": "exp", "ks": 0.5, "clearance": 1e-3, "servo": "paper"}),
    ("side", "side-push", {"learning": "curve", "model": "exp-fit", "dirt_response": "front"},
     {"learning": "curve", "model": "exp-fit", "dirt_response": "front"}),
    ("assembly", "assemble", {}, {}),
    ("assembly", "assemble", {"theta_n_deg": 20.0, "eps_as_um": 10.0},
     {"theta_n": np.deg2rad(20.0), "eps_as": 10 * UM}),
    ("assembly", "assemble", {"planner": "greedy"}, {"planner": "greedy"}),
    ("assembly-3", "assemble", {"n_spheres": 3, "arrangement": "triangle"}, {"arrangement": "triangle"}),
    ("assembly-4", "assemble", {"eps_as_um": 8.0, "max_attempts": 20}, {"eps_as": 8 * UM, "max_attempts": 20}),
]


@pytest.mark.parametrize("kind, task, rig_options, study_options", CASES)
def test_study_and_rig_controllers_are_equal_block_for_block(kind, task, rig_options, study_options):
    rig = build_task(task, first_observation(kind), rig_options).diagram
    study = push_loop(Experiment(kind, task=study_options, variability=Variability())).blocks["controller"]
    assert structure(rig) == structure(study)
    assert structure(rig) == structure(experiment_controller(Experiment(kind, task=study_options)))


def test_the_comparison_sees_a_different_parameter():
    """The equality above is not vacuous: one changed option changes the structure."""
    obs = first_observation("front")
    a = build_task("front-push", obs, {"kc": 0.5}).diagram
    b = build_task("front-push", obs, {"kc": 0.5000001}).diagram
    c = build_task("front-push", obs, {"kc": 0.5, "servo": "paper"}).diagram
    assert structure(a) != structure(b)
    assert structure(a) != structure(c)
    assert structure(a) == structure(build_task("front-push", obs, {"kc": 0.5}).diagram)


def test_both_paths_build_through_one_function(monkeypatch):
    """The rig's registry and the studies' experiments reach :func:`magctl.loops.controller` and nothing else."""
    calls = []
    real = magctl.loops.controller

    def spy(*args, **kw):
        calls.append(inspect.stack()[1].function)
        return real(*args, **kw)

    monkeypatch.setattr(magctl.loops, "controller", spy)
    monkeypatch.setattr(magctl.rig.tasks, "controller", spy)
    build_task("side-push", first_observation("side"), {})
    experiment_controller(Experiment("side"))
    assert calls == ["_build", "experiment_controller"]


def test_replayed_options_rebuild_the_same_controller():
    """The rig logs resolved options; building from them gives the identical controller (replay)."""
    obs = first_observation("side")
    task = build_task("side-push", obs, {"ks": 0.7, "clearance_um": 900.0})
    again = build_task("side-push", obs, task.options)
    assert structure(again.diagram) == structure(task.diagram)
    assert task.options["clearance_m"] == pytest.approx(900 * UM)


@pytest.mark.parametrize("kind, options", [("assembly-3", {"n_spheres": 3, "arrangement": "triangle"}),
                                           ("assembly-3", {"clearance_um": 800.0, "planner": "greedy"})])
def test_the_planned_assembly_logs_the_options_it_runs_and_replays_them(kind, options):
    """The planned assembly's logged options are the values its task runs with (its own record's defaults:
    ``[plan]``'s repositioning keep-out, not the side push's), and rebuilding from them gives the same
    controller."""
    obs = first_observation(kind)
    task = build_task("assemble", obs, options)
    planned = task.diagram.blocks["task"]
    assert task.options["clearance_m"] == pytest.approx(planned.clearance)
    assert planned.clearance == pytest.approx(options.get("clearance_um", 650.0) * UM)
    assert task.options["planner"] == options.get("planner", "optimal")
    again = build_task("assemble", obs, task.options)
    assert structure(again.diagram) == structure(task.diagram)
