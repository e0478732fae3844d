"""Every block's compiled kernel against its numpy form, through the compiled engine.

Each block with a kernel (``Block.kernel()``) is built as in the block contract
(``test_block_contract.FACTORIES`` and ``VARIANTS``), wrapped in a one-block diagram whose inputs and
outputs are the block's own, and simulated by both engines with the same plausible inputs and seed:
every output at every step and the final state must agree to 1e-12 relative (integers and flags
exactly), and a trial run alone (``trials=[k]``) must give the batch's row ``k``.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_block_contract import BATCH, BLOCKS, FACTORIES, VARIANTS, _build, _random_inputs

from magctl.core.block import STREAM, flat_state_vars, state_get
from magctl.core.compiled import NotCompilable
from magctl.core.diagram import Diagram
from magctl.core.simulate import simulate

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


def compare_engines(block, overrides, steps=STEPS):
    d = wrapped(block)
    u = input_series(block, overrides, steps)
    ref = simulate(d, steps, batch=BATCH, seed=11, inputs=u, check_finite=False)
    got = simulate(d, steps, batch=BATCH, seed=11, inputs=u, check_finite=False, engine="compiled")
    for name in block.outputs:
        assert_close(ref[name], got[name], f"{block.name}.{name}")
    for (keys, var) in flat_state_vars(block.state_vars()):
        if var.dtype == STREAM:
            continue
        where = f"{block.name} final state {'.'.join(keys)}"
        assert_close(state_get(ref.final_state["leaves"][0], keys), state_get(got.final_state["leaves"][0], keys),
                     where)
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


@pytest.mark.parametrize("name", sorted(VARIANTS))
def test_kernel_variants_match_the_numpy_form(name):
    block = VARIANTS[name]()
    if block.kernel() is None:
        pytest.skip(f"{name}: no kernel")
    compare_engines(block, {})


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
