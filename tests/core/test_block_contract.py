"""The block contract, for every concrete Block in the package.

Each block is built with small realistic arguments and stepped a few frames with a batch of 3 and
plausible inputs. At every step, against deep copies taken before the calls:

* ``output`` writes nothing into the state, and gives the same outputs when called again;
* ``update`` and ``step`` never mutate the state they are given;
* ``step`` equals ``output`` followed by ``update`` (same outputs, same next state);
* a block without feedthrough gives its outputs without inputs;
* the state holds exactly the declared entries (``state_vars``), with the declared shapes and dtypes.

Blocks are discovered by walking ``magctl`` with pkgutil: a new block class without an entry in
``FACTORIES`` fails :func:`test_every_block_has_a_factory`.
"""

from __future__ import annotations

import copy
import dataclasses
import importlib
import inspect
import pkgutil

import numpy as np
import pytest

import magctl
from magctl.core.block import STREAM, SUBSTATE, Block
from magctl.core.random import TrialStreams
from magctl.core.units import UM

BATCH = 3
STEPS = 4


# --- discovery ----------------------------------------------------------------------------------------
def _block_classes() -> dict[str, type]:
    found = {}
    for mod in pkgutil.walk_packages(magctl.__path__, "magctl."):
        if mod.name.startswith("magctl.cli") or mod.name == "magctl.__main__":
            continue
        module = importlib.import_module(mod.name)
        for _, cls in inspect.getmembers(module, inspect.isclass):
            if issubclass(cls, Block) and cls is not Block and cls.__module__.startswith("magctl."):
                other = found.setdefault(cls.__name__, cls)
                assert other is cls, f"two block classes named {cls.__name__}: {other} and {cls}"
    return found


# --- plausible inputs ----------------------------------------------------------------------------------
def _plausible(port, rng: np.random.Generator, batch: int) -> np.ndarray:
    shape = (batch, *port.shape)
    if port.dtype == "bool":
        return rng.random(shape) < 0.3
    scale = {"m": 1e-3, "m/s": 2e-4, "T": 3e-3, "1/s": 30.0, "rad": 1.0}.get(port.unit, 1.0)
    if port.unit == "m":
        return 1e-3 + scale * rng.random(shape)  # inside the camera's field of view and the test workspaces
    if port.unit in ("1/s", "m/s") or (port.unit == "1" and len(port.shape) == 2):  # frequencies, speeds, images
        return scale * rng.random(shape)
    return scale * rng.standard_normal(shape)


def _random_inputs(block, seed=0, overrides=None):
    overrides = overrides or {}

    def make(k):
        rng = np.random.default_rng([seed, k])
        u = {name: _plausible(p, rng, BATCH) for name, p in block.inputs.items()}
        for name, fn in overrides.items():
            u[name] = fn(rng, k)
        return u

    return make


# --- factories: block and input maker per class --------------------------------------------------------
# Keyed by class name and given the discovered class, so a block that moves to another module keeps its
# entry; an entry is ``make(cls)`` or ``(make(cls), {input: fn(rng, k)})`` for inputs that need care.
def _diagram(cls):
    from magctl.core.linear import PI, Delay, Gain, Integrator
    from magctl.core.nonlinear import GaussianNoise

    inner = cls("inner", [Gain("g", 0.5, shape=(2,)), Integrator("i", shape=(2,), out_unit="1"),
                          GaussianNoise("n", 0.1, shape=(2,))],
                [("g.y", "i.u"), ("i.y", "n.u")], inputs={"x": "g.u"}, outputs={"y": "n.y"})
    return cls("outer", [inner, Delay("d", 2, shape=(2,)), PI("pi", 1.0, 0.5, shape=(2,), limit=0.8)],
               [("inner.y", "d.u"), ("d.y", "pi.e")], inputs={"x": "inner.x"},
               outputs={"y": "pi.u", "sat": "pi.saturated"})


def _robot_params():
    from magctl.plant.robot import load_robot

    return load_robot()


FIELD = {"freq": lambda rng, k: 20.0 + 30.0 * rng.random(BATCH),
         "freq_delivered": lambda rng, k: 20.0 + 30.0 * rng.random(BATCH)}
ROBOT_NEAR = {"position": lambda rng, k: 1.5e-3 + 1e-4 * rng.standard_normal((BATCH, 2)),
              "velocity": lambda rng, k: 3e-4 * rng.standard_normal((BATCH, 2))}
NEAR = {"robot_est": lambda rng, k: np.array([1.0e-3, 1.0e-3]) + 1e-3 * rng.random((BATCH, 2)),
        "spheres_est": lambda rng, k: (np.array([[1.6e-3, 1.5e-3], [2.0e-3, 1.5e-3]])
                                       + 2e-5 * rng.random((BATCH, 2, 2))),
        "lost": lambda rng, k: rng.random(BATCH) < 0.2}
SPHERES = [[1.6e-3, 1.5e-3], [2.5e-3, 2.5e-3]]

def _pair():
    from magctl.control.arrangement import arrangement

    return arrangement("pair")


def _release_law():
    from magctl.control.release_model import release_policy_law

    return release_policy_law(eps=75 * UM, goal=750 * UM)


def _curve_law():
    from magctl.control.curve_learning import curve_learning_law

    return curve_learning_law()


CLEAR = {"robot_est": lambda rng, k: np.array([1.2e-3, 2.4e-3]) + 2e-5 * rng.random((BATCH, 2)),
         "heading_est": lambda rng, k: 0.1 * rng.standard_normal(BATCH),
         "spheres_est": lambda rng, k: np.array([[3.6e-3, 1.0e-3], [3.9e-3, 1.2e-3]]) + np.zeros((BATCH, 2, 2)),
         "lost": lambda rng, k: rng.random(BATCH) < 0.1}
"""Observations of a robot far from the spheres (the excitation sweep drives only there)."""


def _short_sweep():
    from magctl.control.excitation import ExcitationParams

    return ExcitationParams.resolve(hold=0.04, pause=0.04, segment=0.1, min_segment=0.05)


FACTORIES = {
    # core
    "Constant": lambda cls: cls("c", [1.0, 2.0], shape=(2,)),
    "Gain": lambda cls: cls("g", [[1.0, 2.0], [0.0, 1.0], [3.0, 0.0]], shape=(2,)),
    "Sum": lambda cls: cls("s", "+-+", shape=(2,)),
    "Delay": lambda cls: cls("d", 2, shape=(2,)),
    "Integrator": lambda cls: cls("i", shape=(2,)),
    "PI": lambda cls: cls("pi", 2.0, 1.0, shape=(2,), limit=1.5),
    "StateSpace": lambda cls: cls("ss", [[0.9, 0.1], [0.0, 0.8]], [[1.0], [0.5]], [[1.0, 0.0]], [[0.2]]),
    "NormSaturation": lambda cls: cls("sat", 1.0),
    "GaussianNoise": lambda cls: cls("noise", 0.3, shape=(2,)),
    "Diagram": _diagram,
    # plant
    "CoilActuator": (lambda cls: cls("coils"), FIELD),
    "StickSlipRobot": (lambda cls: cls("robot", position=(1e-3, 1e-3)), FIELD),
    "Drive": lambda cls: cls("drive"),
    "ActuatedRobot": lambda cls: cls("plant", position=(1e-3, 1e-3)),
    "Spheres": (lambda cls: cls(SPHERES), ROBOT_NEAR),
    "FieldGait": (lambda cls: cls("gait", _robot_params()), FIELD),
    "StraightToTarget": (lambda cls: cls("servo", v_max=1e-3),
                         {"target": lambda rng, k: np.array([[2e-3, 1e-3]] * BATCH),
                          "position": lambda rng, k: 1e-3 + 1e-4 * rng.random((BATCH, 2))}),
    "StandinSpheres": (lambda cls: cls("spheres", SPHERES, 250 * UM, release_mean=300 * UM, release_std=75 * UM,
                                       side_range=600 * UM, start_robot=(1.5e-3, 1.5e-3)),
                       {"position": lambda rng, k: np.array([[1.5e-3 + 1e-4 * k, 1.5e-3]] * BATCH)}),
    "StandinTracker": lambda cls: cls("tracker", 2, 2.5e-3, blackout=(0.04, 0.08)),
    "KinematicRobot": lambda cls: cls("robot", start=(1e-3, 1e-3)),
    # sensing
    "Camera": lambda cls: cls("camera", n_spheres=2, latency_frames=2, drop_probability=0.2, position_noise_px=0.5),
    "Tracker": lambda cls: cls("tracker", n_spheres=2, mode="kalman", predict_frames=2),
    "Blackout": lambda cls: cls("blackout", window=(0.04, 0.08)),
    # control
    "Servo": lambda cls: cls("servo", speed_cap_input=True, hold_input=True),
    "LearningLaw": lambda cls: cls("law", 0.8, initial=1e-4),
    "ReleasePolicyLaw": (lambda cls: _release_law(), {"e": lambda rng, k: 200 * UM * rng.standard_normal(BATCH)}),
    "CurveLearningLaw": (lambda cls: _curve_law(),
                         {"gap": lambda rng, k: (380 + 300 * rng.random(BATCH)) * UM,
                          "displacement": lambda rng, k: 80 * UM * rng.random(BATCH)}),
    "Planner": (lambda cls: cls("planner", n_spheres=2, bounds=(0.0, 0.0, 3e-3, 3e-3), cell=50e-6),
                {"goal": lambda rng, k: np.array([[2.8e-3, 2.8e-3]] * BATCH), **NEAR}),
    "ArrivalStatus": lambda cls: cls("status"),
    "Patrol": (lambda cls: cls("patrol", [[1e-3, 1e-3], [1.5e-3, 1.5e-3]], 4e-4), NEAR),
    "FrontPushTask": (lambda cls: cls("front", goal=(2.5e-3, 1.5e-3), n_spheres=2, arrive_tol=500 * UM,
                                      settle_frames=1), NEAR),
    "FrontAssemblyTask": (lambda cls: cls("front_assembly", arrive_tol=500 * UM, settle_frames=1), NEAR),
    "SidePushTask": (lambda cls: cls("side", goal=(2.5e-3, 1.5e-3), n_spheres=2, arrive_tol=500 * UM,
                                     settle_frames=1), NEAR),
    "AssemblyTask": (lambda cls: cls("assembly", arrive_tol=500 * UM, settle_frames=1), NEAR),
    "FrontThenSideAssemblyTask": (lambda cls: cls("front_side", arrive_tol=500 * UM, settle_frames=1), NEAR),
    "PlannedAssemblyTask": (lambda cls: cls("planned", n_spheres=2, arrangement="pair", arrive_tol=500 * UM,
                                            settle_frames=1), NEAR),
    "PassPlanner": (lambda cls: cls(_pair()), {"spheres": NEAR["spheres_est"], "robot": NEAR["robot_est"]}),
    "Excitation": (lambda cls: cls("sweep", n_spheres=2, params=_short_sweep()), CLEAR),
}

BLOCKS = _block_classes()


def _build(name):
    entry = FACTORIES[name]
    make, overrides = entry if isinstance(entry, tuple) else (entry, {})
    return make(BLOCKS[name]), overrides


def _variants() -> dict:
    """Other configurations of the same classes, whose code paths differ enough to be run too."""
    from magctl.control.push.assembly import AssemblyTask, FrontThenSideAssemblyTask
    from magctl.control.push.front import FrontPushTask
    from magctl.control.push.side import SidePushTask
    from magctl.control.servo import Servo
    from magctl.core.linear import PI
    from magctl.plant.fluid.params import sphere_params
    from magctl.plant.robot import StickSlipRobot
    from magctl.plant.sphere import Spheres
    from magctl.plant.standin import KinematicRobot, StandinTracker
    from magctl.sensing.camera import Camera
    from magctl.sensing.tracker import Tracker

    return {
        "PI, no limit": lambda: PI("pi", 1.0, 0.3, shape=(2,)),
        "Camera, no latency": lambda: Camera("camera", n_spheres=1, latency_frames=0, drop_probability=0.3,
                                             position_noise_px=0.5),
        "Camera, 1 frame latency": lambda: Camera("camera", n_spheres=1, latency_frames=1, drop_probability=0.3,
                                                  position_noise_px=0.5),
        "Camera, 3 frames latency, no spheres": lambda: Camera("camera", n_spheres=0, latency_frames=3,
                                                               drop_probability=0.3, position_noise_px=0.5),
        "Tracker, raw, NaN on loss": lambda: Tracker("tracker", n_spheres=1, mode="raw", on_loss="nan"),
        "Servo, basic PI": lambda: Servo("servo", anti_windup=False, constant_speed=True),
        "Servo, no optional inputs": lambda: Servo("servo"),
        "SidePushTask, eq 22 model": lambda: SidePushTask("side", goal=(2.5e-3, 1.5e-3), model="exp",
                                                          arrive_tol=500 * UM, settle_frames=1),
        "SidePushTask, curve learning": lambda: SidePushTask("side", goal=(2.5e-3, 1.5e-3), learning="curve",
                                                             model="exp-fit", arrive_tol=500 * UM, settle_frames=1),
        "SidePushTask, curve learning, front push on dirt": lambda: SidePushTask(
            "side", goal=(2.5e-3, 1.5e-3), learning="curve", model="exp-fit", dirt_response="front",
            arrive_tol=500 * UM, settle_frames=1),
        "SidePushTask, fixed gap": lambda: SidePushTask("side", goal=(2.5e-3, 1.5e-3), fixed_gap=500 * UM,
                                                        arrive_tol=500 * UM, settle_frames=1),
        "SidePushTask, curve learning, fixed gap": lambda: SidePushTask(
            "side", goal=(2.5e-3, 1.5e-3), learning="curve", model="exp-fit", fixed_gap=450 * UM, arrive_tol=500 * UM,
            settle_frames=1),
        "FrontPushTask, release model": lambda: FrontPushTask("front", goal=(2.5e-3, 1.5e-3), n_spheres=2,
                                                              learning="release", arrive_tol=500 * UM, settle_frames=1),
        "AssemblyTask, curve learning": lambda: AssemblyTask("assembly", learning="curve", model="exp-fit",
                                                             arrive_tol=500 * UM, settle_frames=1),
        "FrontThenSideAssemblyTask, curve learning": lambda: FrontThenSideAssemblyTask(
            "front_side", learning="curve", model="exp-fit", arrive_tol=500 * UM, settle_frames=1),
        "StickSlipRobot, no variability": lambda: StickSlipRobot("robot", variability=False),
        "KinematicRobot, steer input": lambda: KinematicRobot("robot", start=(1e-3, 1e-3), steer_input=True),
        "StandinTracker, sphere loss": lambda: StandinTracker("tracker", 2, 1.6e-3, sphere_loss=(0.3, np.inf)),
        # eq 4-5 and 9 as printed, with adhesion, sticky patches and release scatter drawn at step 0
        "Spheres, paper drag, adhesion, scattered": lambda: Spheres(
            SPHERES, drag_mode="paper",
            params=dataclasses.replace(sphere_params(), adhesion=True, sticky_probability=0.5, release_scatter=0.3)),
    }


VARIANTS = _variants()


def test_every_block_has_a_factory():
    missing = sorted(set(BLOCKS) - set(FACTORIES))
    assert not missing, f"block classes without a factory in tests/core/test_block_contract.py: {missing}"


# --- state comparison ----------------------------------------------------------------------------------
def _same(a, b, where="state") -> None:
    """Assert ``a`` and ``b`` hold the same values (arrays bit for bit, NaN equal to NaN)."""
    if isinstance(a, TrialStreams) or isinstance(b, TrialStreams):
        # a stream is a memo of a fixed sequence, read by position: not part of the compared values
        assert type(a) is type(b), where
        return
    if isinstance(a, np.random.Generator):
        assert a.bit_generator.state == b.bit_generator.state, f"{where}: generator advanced"
        return
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        a, b = np.asarray(a), np.asarray(b)
        assert a.shape == b.shape, f"{where}: shape {a.shape} vs {b.shape}"
        assert a.dtype == b.dtype, f"{where}: dtype {a.dtype} vs {b.dtype}"
        assert np.array_equal(a, b, equal_nan=a.dtype.kind in "fc"), f"{where}: values differ"
        return
    if isinstance(a, dict):
        assert isinstance(b, dict) and set(a) == set(b), f"{where}: keys {sorted(a)} vs {sorted(b)}"
        for k in a:
            _same(a[k], b[k], f"{where}[{k!r}]")
        return
    if isinstance(a, (list, tuple)):
        assert type(a) is type(b) and len(a) == len(b), f"{where}: {a!r} vs {b!r}"
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _same(x, y, f"{where}[{i}]")
        return
    if hasattr(a, "__dict__") and not isinstance(a, type):
        assert type(a) is type(b), where
        _same(vars(a), vars(b), f"{where}.{type(a).__name__}")
        return
    assert a == b or (a != a and b != b), f"{where}: {a!r} vs {b!r}"


def _check_declared(block, state, batch, where=None) -> None:
    where = where or block.name
    variables = block.state_vars() if not isinstance(block, tuple) else block
    _check_vars(variables, state, batch, where)


def _check_vars(variables, state, batch, where):
    assert isinstance(state, dict), where
    names = [v.name for v in variables]
    assert len(names) == len(set(names)), f"{where}: a state entry declared twice"
    assert set(state) == set(names), f"{where}: state entries {sorted(state)}, declared {sorted(names)}"
    for v in variables:
        val = state[v.name]
        if v.dtype == SUBSTATE:
            _check_vars(v.sub, val, batch, f"{where}.{v.name}")
        elif v.dtype == STREAM:
            assert val is None or isinstance(val, TrialStreams), f"{where}.{v.name}: {type(val)}"
        elif v.dtype == "object":
            continue
        elif v.batched:
            assert isinstance(val, np.ndarray), f"{where}.{v.name}: {type(val)}"
            assert val.shape == (batch, *v.shape), f"{where}.{v.name}: shape {val.shape}, declared {v.shape}"
            assert val.dtype.kind == np.dtype(v.dtype).kind, f"{where}.{v.name}: dtype {val.dtype}, declared {v.dtype}"
        else:
            assert np.shape(val) == v.shape, f"{where}.{v.name}: shape {np.shape(val)}, declared {v.shape}"
            assert np.asarray(val).dtype.kind == np.dtype(v.dtype).kind, f"{where}.{v.name}"


def _initial(block):
    from magctl.core.diagram import Diagram

    if isinstance(block, Diagram):
        return block.initial_state(BATCH, seed=5)
    rng = TrialStreams.for_block(5, range(BATCH), block.name) if block.uses_random else None
    return block.initial_state(BATCH, rng)


def _diagram_inputs(diagram, k):
    rng = np.random.default_rng([7, k])
    return {name: _plausible(p, rng, BATCH) for name, p in diagram.inputs.items()}


def run_contract(block, make_inputs, steps=STEPS, declared=True) -> None:
    """Step ``block`` and check the contract at every step (see the module docstring)."""
    from magctl.core.diagram import Diagram

    state = _initial(block)
    is_diagram = isinstance(block, Diagram)
    for k in range(steps):
        if is_diagram:
            _check_declared(block, state, BATCH)
            for lf, st in zip(block.schedule.leaves, state["leaves"], strict=True):
                _check_declared(lf.block, st, BATCH, lf.path)
        elif declared:
            _check_declared(block, state, BATCH)
        u = make_inputs(k)
        before = copy.deepcopy(state)
        y = block.output(state, u)
        _same(state, before, f"{block.name}: state after output() at step {k}")
        _same(block.output(state, u), y, f"{block.name}: output() called twice at step {k}")
        if not block.feedthrough:
            _same(block.output(state, {}), y, f"{block.name}: output() without inputs at step {k}")
        nxt = block.update(state, u)
        _same(state, before, f"{block.name}: state after update() at step {k}")
        y2, nxt2 = block.step(state, u)
        _same(state, before, f"{block.name}: state after step() at step {k}")
        _same(y2, y, f"{block.name}: step() outputs vs output() at step {k}")
        _same(nxt2, nxt, f"{block.name}: step() next state vs update() at step {k}")
        assert set(y) == set(block.outputs), f"{block.name}: outputs {sorted(y)}"
        for name, port in block.outputs.items():
            assert np.shape(y[name]) == (BATCH, *port.shape), f"{block.name}.{name}: shape {np.shape(y[name])}"
        state = nxt


@pytest.mark.parametrize("name", sorted(set(BLOCKS) & set(FACTORIES)))
def test_block_contract(name):
    block, overrides = _build(name)
    from magctl.core.diagram import Diagram

    inputs = (lambda k: _diagram_inputs(block, k)) if isinstance(block, Diagram) else _random_inputs(
        block, overrides=overrides)
    run_contract(block, inputs)


@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_block_contract_variants(variant):
    block = VARIANTS[variant]()
    run_contract(block, _random_inputs(block))


def test_image_mode_camera_and_particle_tracker_keep_the_contract():
    """The rig's image path: rendered frames with noise, particle filters stepped on copies."""
    from magctl.sensing.camera import Camera
    from magctl.sensing.tracker import Tracker

    cam = Camera("camera", n_spheres=1, mode="images", latency_frames=1)
    scene = {"position": lambda rng, k: np.array([[1.5e-3, 1.2e-3]] * BATCH),
             "heading": lambda rng, k: np.zeros(BATCH),
             "spheres": lambda rng, k: np.array([[[2.2e-3, 1.2e-3]]] * BATCH)}
    run_contract(cam, _random_inputs(cam, overrides=scene), steps=2)
    trk = Tracker("tracker", n_spheres=1, mode="particle", init_robot=(1.5e-3, 1.2e-3), init_spheres=[[2.2e-3, 1.2e-3]])
    cam_state = _initial(cam)
    frame = cam.output(cam_state, {})["image"]
    run_contract(trk, lambda k: {"image": frame, "valid": np.ones(BATCH, bool)}, steps=2)


def test_the_contract_check_catches_an_update_that_mutates_its_state():
    """The checks can fail: an Integrator whose update writes into the state it was given."""
    from magctl.core.linear import Integrator

    class Leaky(Integrator):
        def update(self, state, u):
            state["x"] = state["x"] + self.dt * u["u"]
            return state

    blk = Leaky("leaky", shape=(2,))
    with pytest.raises(AssertionError, match="state after update"):
        run_contract(blk, _random_inputs(blk))


def test_the_contract_check_catches_an_output_that_caches_in_state():
    from magctl.core.linear import Gain

    class Stash(Gain):
        def output(self, state, u):
            state["_seen"] = u["u"]
            return super().output(state, u)

    blk = Stash("stash", 2.0)
    with pytest.raises(AssertionError, match="state after output"):
        run_contract(blk, _random_inputs(blk))


def test_the_contract_check_catches_a_sequential_draw():
    """A block drawing noise sequentially (a count of its own, not the state's position) gives different
    numbers on a second call."""
    from magctl.core.nonlinear import GaussianNoise

    class Sequential(GaussianNoise):
        calls = 0

        def output(self, state, u):
            self.calls += 1
            return {"y": u["u"] + self.sigma * state["rng"].standard_normal(self.inputs["u"].shape, at=self.calls)}

    blk = Sequential("seq", 1.0)
    with pytest.raises(AssertionError, match="twice"):
        run_contract(blk, _random_inputs(blk))
