"""Every block's kernel against its numpy reference, through both engines.

Each block with a kernel (``Block.kernel()``) is built as in the block contract
(``test_block_contract.FACTORIES`` and ``VARIANTS``), wrapped in a one-block diagram whose inputs and
outputs are the block's own, and simulated with the same plausible inputs and seed three ways: its
numpy reference (``tests/reference``), its kernel through the interpreted engine's driver, its kernel
fused by the compiled engine. Every output at every step and the final state must agree to 1e-12
relative (integers and flags exactly), and a trial run alone (``trials=[k]``) must give the batch's
row ``k``.
"""

from __future__ import annotations

import numpy as np
import pytest
from reference import reference_of
from test_block_contract import BATCH, BLOCKS, FACTORIES, VARIANTS, _build, _random_inputs

from magctl.core.block import STREAM, flat_state_vars, state_get
from magctl.core.compiled import NotCompilable
from magctl.core.diagram import Diagram
from magctl.core.simulation import simulate
from magctl.core.units import UM

STEPS = 40
RTOL = 1e-12


def wrapped(block) -> Diagram:
    """``block`` alone in a diagram that exports every input and output under the port's name."""
    return Diagram("w", [block], inputs={p: f"{block.name}.{p}" for p in block.inputs},
                   outputs={p: f"{block.name}.{p}" for p in block.outputs}, dt=block.dt)


def input_series(block, overrides, steps=STEPS, seed=0) -> dict[str, np.ndarray]:
    make = _random_inputs(block, seed, overrides)
    per_step = [make(k) for k in range(steps)]
    return {p: np.stack([np.asarray(u[p], dtype=port.dtype) for u in per_step], axis=1)
            for p, port in block.inputs.items()}


def assert_close(a, b, where):
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape, f"{where}: shape {a.shape} vs {b.shape}"
    if a.dtype.kind == "f":
        np.testing.assert_allclose(b, a, rtol=RTOL, atol=0, equal_nan=True, err_msg=where)
    else:
        assert np.array_equal(a, b), f"{where}: values differ"


def _agree(ref, got, block, label):
    for name in block.outputs:
        assert_close(ref[name], got[name], f"{block.name}.{name} ({label})")
    for (keys, var) in flat_state_vars(block.state_vars()):
        if var.dtype == STREAM:
            continue
        where = f"{block.name} final state {'.'.join(keys)} ({label})"
        assert_close(state_get(ref.final_state["leaves"][0], keys), state_get(got.final_state["leaves"][0], keys),
                     where)


def compare_engines(block, overrides, steps=STEPS):
    """The block's kernel, run by the interpreted engine (its driver) and by the compiled engine, against its
    numpy reference in ``tests/reference`` (for a block that still carries a numpy form of its own, against
    that)."""
    d = wrapped(block)
    u = input_series(block, overrides, steps)
    numpy_form = reference_of(block)
    ref_block = block if numpy_form is None else numpy_form
    ref = simulate(wrapped(ref_block), steps, batch=BATCH, seed=11, inputs=u, check_finite=False,
                   engine="interpreted")
    got = simulate(d, steps, batch=BATCH, seed=11, inputs=u, check_finite=False, engine="compiled")
    _agree(ref, got, block, "compiled")
    if numpy_form is not None:
        interpreted = simulate(d, steps, batch=BATCH, seed=11, inputs=u, check_finite=False, engine="interpreted")
        _agree(ref, interpreted, block, "interpreted, through the kernel driver")
    alone = simulate(d, steps, batch=1, seed=11, trials=[BATCH - 1], check_finite=False, engine="compiled",
                     inputs={p: v[BATCH - 1:] for p, v in u.items()})
    for name in block.outputs:
        assert_close(ref[name][BATCH - 1:], alone[name], f"{block.name}.{name}, trial {BATCH - 1} alone")


def _with_kernels() -> list[str]:
    names = []
    for name in sorted(set(BLOCKS) & set(FACTORIES)):
        block, _ = _build(name)
        if not isinstance(block, Diagram) and block.kernel() is not None:
            names.append(name)
    return names


WITH_KERNELS = _with_kernels()
CORE = ["Constant", "Gain", "Sum", "Delay", "Integrator", "PI", "StateSpace", "NormSaturation", "GaussianNoise"]


def test_the_core_blocks_have_kernels():
    assert set(CORE) <= set(WITH_KERNELS), sorted(set(CORE) - set(WITH_KERNELS))


@pytest.mark.parametrize("name", WITH_KERNELS)
def test_kernel_matches_the_numpy_form(name):
    block, overrides = _build(name)
    compare_engines(block, overrides)


KERNEL_VARIANTS = sorted(VARIANTS)


def test_every_variant_has_a_kernel():
    """The push laws (eq 13, eq 18, the curve and release laws, the dirt response) all compile: no variant of a
    kernelled class falls back to the interpreted engine."""
    missing = [name for name, make in VARIANTS.items() if make().kernel() is None]
    assert not missing, missing


@pytest.mark.parametrize("name", KERNEL_VARIANTS)
def test_kernel_variants_match_the_numpy_form(name):
    compare_engines(VARIANTS[name](), {})


def test_standin_spheres_kernel_side_pass_release_and_separation():
    """The stand-in spheres' paths the factory's straight push does not reach: a side pass (eq 22; also
    with a scale per trial), a release with its per-trial draw when the robot backs off, and spheres
    pushed into each other."""
    from magctl.plant.standin import StandinSpheres

    spheres = [[1.4e-3, 1.5e-3], [1.62e-3, 1.5e-3], [2.0e-3, 1.9e-3]]

    def make(scale):
        return StandinSpheres("spheres", spheres, 250 * UM, release_mean=300 * UM, release_std=75 * UM,
                              side_range=600 * UM, sphere_radius=105 * UM, start_robot=(1.0e-3, 1.5e-3),
                              side_scale=scale)

    def robot(rng, k):     # ahead along +x, then back, then aside; each trial a little off the line
        x = 1.0e-3 + 1e-4 * k if k < 20 else (2.9e-3 - 1e-4 * (k - 20) if k < 30 else 1.9e-3)
        y = 1.5e-3 + (0.0 if k < 30 else 1e-4 * (k - 30))
        return np.array([[x, y + 10 * UM * b] for b in range(BATCH)])

    block = make(1.3)
    compare_engines(block, {"position": robot})
    d = wrapped(block)
    u = input_series(block, {"position": robot})
    ref = simulate(d, STEPS, batch=BATCH, seed=11, inputs=u, check_finite=False)
    assert ref["releases"][:, -1].min() >= 1 and len(set(ref["last_release"][:, -1])) == BATCH   # drawn per trial
    assert np.abs(ref["spheres"][:, -1, 2] - np.array(spheres[2])).max() > 1e-5                   # side pass
    # one scale per trial: row b's (a trial run alone would take the first, in either engine)
    d = wrapped(make([1.0, 0.7, 1.3]))
    ref = simulate(d, STEPS, batch=BATCH, seed=11, inputs=u, check_finite=False)
    got = simulate(d, STEPS, batch=BATCH, seed=11, inputs=u, check_finite=False, engine="compiled")
    for name in ("spheres", "contact", "releases", "last_release"):
        assert_close(ref[name], got[name], name)
    assert len({round(float(x), 9) for x in ref["spheres"][:, 16, 2, 0]}) == BATCH      # passed, scaled


def _field_command(steps: int) -> dict[str, np.ndarray]:
    """A plausible field command: ahead along +x (onto the sphere), back along −x, then up +y; the
    rocking field held, the frequency (the speed) stepped."""
    k = np.arange(steps)
    phi = np.where(k < 120, 0.0, np.where(k < 200, np.pi, np.pi / 2))
    b_static = 1e-3 * np.stack([np.cos(phi), np.sin(phi)], axis=-1)
    freq = np.where(k % 100 < 50, 20.0, 12.0)
    batch = BATCH
    return {"b_static": np.broadcast_to(b_static, (batch, steps, 2)).copy(),
            "b_osc": np.full((batch, steps), 1.45e-3), "freq": np.broadcast_to(freq, (batch, steps)).copy()}


def _compare_diagram(d, inputs, steps, record):
    ref = simulate(d, steps, batch=BATCH, seed=5, inputs=inputs, record=record, check_finite=False)
    got = simulate(d, steps, batch=BATCH, seed=5, inputs=inputs, record=record, check_finite=False,
                   engine="compiled")
    for name in record:
        assert_close(ref[name], got[name], name)
    return ref


def test_the_standin_chain_compiles_and_agrees_with_the_interpreted_engine():
    """Field gait → kinematic robot → stand-in spheres → stand-in tracker, the delivered field as the
    diagram's inputs: 300 frames of a push, a release and a turn, the same in both engines."""
    from magctl.loops import Scene, Variability, plant

    scene = Scene(robot=(1e-3, 1.8e-3), spheres=[[1.6e-3, 1.8e-3]])
    rig = plant(scene, Variability(release_scatter=0.3), kind="standin")
    field = ("b_static_delivered", "b_osc_delivered", "freq_delivered")
    d = Diagram("chain", [b for name, b in rig.blocks.items() if name != "coils"],
                [c for c in rig.connections if not c[0].startswith("coils.")],
                inputs={p: f"gait.{p}" for p in field},
                outputs={"robot_est": "tracker.robot_est", "spheres_est": "tracker.spheres_est"})
    steps = 300
    cmd = _field_command(steps)
    u = {"b_static_delivered": cmd["b_static"], "b_osc_delivered": cmd["b_osc"], "freq_delivered": cmd["freq"]}
    record = ["gait.speed", "gait.heading", "robot.position", "spheres.spheres", "spheres.releases",
              "spheres.last_release", "tracker.robot_est", "tracker.spheres_est", "tracker.lost"]
    ref = _compare_diagram(d, u, steps, record)
    assert ref["spheres.releases"][:, -1].min() >= 1                   # pushed, then released
    assert np.ptp(ref["spheres.spheres"][0, :, 0, 0]) > 1e-4           # the sphere moved


def test_the_standin_rig_plant_compiles_and_agrees_with_the_interpreted_engine():
    """``magctl.loops.plant(scene, kind="standin")`` with one sphere, 300 frames of a field command."""
    from magctl.loops import Scene, plant

    scene = Scene(robot=(1e-3, 1.8e-3), spheres=[[1.6e-3, 1.8e-3]])
    d = plant(scene, kind="standin")
    missing = [name for name, b in d.blocks.items() if b.kernel() is None]
    if missing:
        pytest.skip(f"blocks {missing} have no kernel yet")
    steps = 300
    record = ["coils.b_static_delivered", "gait.speed", "robot.position", "spheres.spheres", "tracker.robot_est",
              "tracker.spheres_est", "tracker.lost"]
    ref = _compare_diagram(d, _field_command(steps), steps, record)
    assert np.ptp(ref["robot.position"][0, :, 0]) > 1e-3                # the field moved the robot
    assert np.ptp(ref["spheres.spheres"][0, :, 0, 0]) > 1e-4            # which pushed the sphere


def test_a_block_without_kernel_is_named_and_the_auto_engine_interprets():
    from magctl.core.block import Block
    from magctl.core.linear import Gain
    from magctl.core.ports import Port

    class Square(Block):
        def __init__(self):
            super().__init__("square", inputs=[Port("u", ())], outputs=[Port("y", ())])

        def output(self, state, u):
            return {"y": u["u"] ** 2}

    d = Diagram("d", [Gain("g", 3.0), Square()], [("g.y", "square.u")], inputs={"x": "g.u"},
                outputs={"y": "square.y"})
    with pytest.raises(NotCompilable, match="'square' \\(Square\\) has no compiled kernel"):
        simulate(d, 5, inputs={"x": 2.0}, engine="compiled")
    auto = simulate(d, 5, inputs={"x": 2.0}, engine="auto")
    assert np.all(auto["y"] == 36.0)


def test_generated_loops_run_without_the_reference_counted_runtime():
    """Kernels allocate nothing, so the generated loops need no NRT, whose atomic counts per array use
    dominate a kernel that holds many state arrays; a diagram still runs and gives the same numbers."""
    from magctl.core.compiled import compile_diagram
    from magctl.core.linear import Gain

    d = wrapped(Gain("g", 2.0))
    assert "_nrt=False" in compile_diagram(d).source
    assert np.all(simulate(d, 3, inputs={"u": 1.5}, engine="compiled")["y"] == 3.0)


def test_engine_name_is_checked():
    from magctl.core.linear import Gain

    d = wrapped(Gain("g", 2.0))
    with pytest.raises(ValueError, match="engine 'fast'"):
        simulate(d, 3, inputs={"u": 1.0}, engine="fast")


def test_a_run_in_chunks_is_the_run_in_one_on_either_engine():
    from magctl.testing import b1_diagram

    d = b1_diagram()
    ref = simulate(d, 600, batch=3, seed=4)
    state, parts = None, []
    for k, engine in enumerate(("interpreted", "compiled", "compiled", "interpreted")):
        r = simulate(d, 150, batch=3, seed=4, state=state, engine=engine)
        state = r.final_state
        parts.append(r["y"])
        assert r.t[0] == pytest.approx(150 * k * d.dt)
    np.testing.assert_allclose(np.concatenate(parts, axis=1), ref["y"], rtol=RTOL, atol=0)
    assert state["tick"] == ref.final_state["tick"] == 600
    # counter-based streams: the interpreted engine continues wherever the compiled one stopped
    first = simulate(d, 20, batch=3, seed=4, engine="compiled")
    rest = simulate(d, 10, batch=3, seed=4, state=first.final_state, engine="interpreted")
    np.testing.assert_allclose(rest["y"], ref["y"][:, 20:30], rtol=RTOL, atol=0)


def test_the_compiled_stepper_is_the_interpreted_step():
    from magctl.core.linear import PI, Delay, Integrator

    d = Diagram("loop", [PI("pi", 1.2, 0.4, shape=(2,), limit=1.0), Integrator("x", shape=(2,), out_unit="1"),
                         Delay("d", 2, shape=(2,))],
                [("pi.u", "x.u"), ("x.y", "d.u")], inputs={"e": "pi.e"}, outputs={"y": "d.y", "sat": "pi.saturated"})
    state = d.initial_state(2, seed=0)
    stepper = d.compile().stepper(state, 2)
    rng = np.random.default_rng(1)
    for _ in range(50):
        e = rng.standard_normal((2, 2))
        ref, state = d.step(state, {"e": e})
        got = stepper.step({"e": e})
        for name in ref:
            assert_close(ref[name], got[name], name)
    for a, b in zip(state["leaves"], stepper.state["leaves"], strict=True):
        for key in a:
            assert_close(a[key], b[key], key)


def test_zero_size_values_have_empty_slots():
    """A port or state entry with no elements (no spheres: shape (0, 2)) compiles into an empty slot."""
    from magctl.core.linear import Constant, Gain

    d = Diagram("d", [Constant("none", np.zeros((0, 2)), shape=(0, 2)), Gain("g", 2.0, shape=(0, 2)),
                      Gain("h", 3.0)],
                [("none.y", "g.u")], inputs={"x": "h.u"}, outputs={"y": "g.y", "z": "h.y"})
    got = simulate(d, 3, batch=2, inputs={"x": 1.5}, engine="compiled")
    assert got["y"].shape == (2, 3, 0, 2)
    assert np.all(got["z"] == 4.5)


def test_the_plant_without_spheres_matches_the_numpy_form():
    """The plant half of the push loop (coils → robot → camera → blackout → tracker, no spheres) under a
    constant field command: 300 frames, both engines, every leaf's outputs and final state."""
    from magctl.loops import Scene, Variability, plant

    d = plant(Scene(), Variability())
    d.compile()
    u = {"b_static": np.array([3e-3, 1e-3]), "b_osc": 2e-3, "freq": 20.0}
    ref = simulate(d, 300, batch=4, seed=3, inputs=u)
    got = simulate(d, 300, batch=4, seed=3, inputs=u, engine="compiled")
    record = [f"{lf.path}.{p}" for lf in d.schedule.leaves for p in lf.block.outputs]
    for name in record:
        assert_close(ref[name], got[name], name)
    assert ref["tracker.lost"][:, -1].all() and not ref["tracker.lost"][:, 0].any()  # it drives out of view
    for i, lf in enumerate(d.schedule.leaves):
        for keys, var in flat_state_vars(lf.block.state_vars()):
            if var.dtype != STREAM:
                assert_close(state_get(ref.final_state["leaves"][i], keys),
                             state_get(got.final_state["leaves"][i], keys), f"{lf.path} final state {'.'.join(keys)}")


def test_the_generated_step_keeps_no_reference_counts_and_the_stepper_matches():
    """The generated functions run without numba's reference counting (kernels take views, never allocate);
    the one-tick stepper (the rig's form) gives what ``simulate`` gives."""
    from magctl.plant.coils import CoilActuator
    from magctl.plant.drive import Drive

    d = Diagram("d", [Drive("drive"), CoilActuator("coils")],
                [("drive.b_static", "coils.b_static"), ("drive.b_osc", "coils.b_osc"), ("drive.freq", "coils.freq")],
                inputs={"speed": "drive.speed", "heading": "drive.heading"}, outputs={"currents": "coils.currents"})
    compiled = d.compile()
    assert "_nrt=False" in compiled.source
    speed = np.array([[1e-4], [3e-4], [2e-3]]) * np.ones((3, 6))
    stepper = compiled.stepper(d.initial_state(3), 3)
    stepped = np.stack([stepper.step({"speed": speed[:, k], "heading": 0.3 * k})["currents"].copy() for k in range(6)],
                       1)   # the outputs are views, overwritten by the next step
    heading = np.broadcast_to(0.3 * np.arange(6), (3, 6))
    ref = simulate(d, 6, batch=3, inputs={"speed": speed, "heading": heading})
    assert_close(ref["currents"], stepped, "stepped currents")


PYTHON_ONLY_MODES = {
    "Camera": ({"output", "update"}, 'mode="images" renders frames (render_frame): kernel() is None'),
    "Tracker": ({"step", "output", "update"}, 'mode="particle" runs a particle filter per trial: kernel() is None'),
}
"""Mixed-mode blocks (library class name → the methods it defines, and why): a configuration without a kernel
keeps its Python path, so these methods dispatch — that mode in Python, every other configuration to the base
class, which runs the kernel."""


def test_a_kernelled_block_has_one_implementation():
    """A block whose numpy form moved to ``tests/reference`` defines no output, update or step of its own: its
    kernel is its behaviour in both engines. Only the mixed-mode blocks of ``PYTHON_ONLY_MODES`` define the
    methods listed there, documented, and those run the kernel in the kernelled configuration of the block
    contract."""
    from reference import REFERENCES
    from test_block_contract import _initial

    for lib, ref in REFERENCES.items():
        assert issubclass(ref, lib)
        own = {"output", "update", "step"} & set(vars(lib))
        allowed, _why = PYTHON_ONLY_MODES.get(lib.__name__, (set(), ""))
        assert own <= allowed, f"{lib.__name__} still defines {sorted(own - allowed)} beside its kernel"
        assert own == allowed, f"{lib.__name__} no longer defines {sorted(allowed - own)}: update PYTHON_ONLY_MODES"
        for method in sorted(own):
            assert getattr(lib, method).__doc__, f"{lib.__name__}.{method}: an undocumented dispatcher"
            block, overrides = _build(lib.__name__)
            assert block.kernel() is not None
            getattr(block, method)(_initial(block), _random_inputs(block, overrides=overrides)(0))
            driver = block.kernel_driver()
            assert driver is not None and driver._loops, f"{lib.__name__}.{method} did not run the kernel"


def test_generated_code_changes_with_any_module_a_kernel_inlines():
    """numba's cache checks only the file that defines a function; the generated loops hash every magctl module
    their kernels draw on, so editing an inlined helper's module (not the kernel's own) recompiles them."""
    from magctl.core.codegen import kernel_modules

    found = kernel_modules(["magctl.control.push.kernels"])
    assert {"magctl.control.kernels", "magctl.control.status", "magctl.control.phases"} <= found
    assert "magctl.core.philox" in kernel_modules(["magctl.core.kernels"])
