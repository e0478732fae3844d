"""Every wiring error is raised at build time and names the culprit."""

import numpy as np
import pytest

from magctl.core import (
    PI,
    AlgebraicLoopError,
    Block,
    Constant,
    Delay,
    Diagram,
    Gain,
    Integrator,
    Port,
    RateError,
    Sum,
    WiringError,
)


def test_unconnected_input_names_block_and_port():
    with pytest.raises(WiringError, match=r"input k\.u is not connected"):
        Diagram("d", [Gain("k", 2.0), Constant("c", 1.0)])


def test_shape_mismatch_names_both_ends():
    c = Constant("c", [1.0, 2.0], shape=(2,))
    with pytest.raises(WiringError, match=r"shape mismatch: c\.y is \[2\] but k\.u expects \[\]"):
        Diagram("d", [c, Gain("k", 2.0)], [("c.y", "k.u")])


def test_unit_mismatch_names_units():
    c = Constant("c", 1.0, unit="m")
    with pytest.raises(WiringError, match=r"unit mismatch: c\.y is in 'm' but k\.u expects 's'"):
        Diagram("d", [c, Gain("k", 2.0, in_unit="s")], [("c.y", "k.u")])


def test_two_drivers_for_one_input():
    a, b = Constant("a", 1.0), Constant("b", 2.0)
    with pytest.raises(WiringError, match=r"input k\.u has two drivers: a\.y and b\.y"):
        Diagram("d", [a, b, Gain("k", 1.0)], [("a.y", "k.u"), ("b.y", "k.u")])


def test_unknown_block_and_port():
    with pytest.raises(WiringError, match=r"no block 'nope'"):
        Diagram("d", [Gain("k", 1.0)], [("nope.y", "k.u")])
    with pytest.raises(WiringError, match=r"block 'c' has no output 'z'"):
        Diagram("d", [Constant("c", 1.0), Gain("k", 1.0)], [("c.z", "k.u")])
    with pytest.raises(WiringError, match=r"'block.port'"):
        Diagram("d", [Constant("c", 1.0), Gain("k", 1.0)], [("c", "k.u")])


def test_duplicate_block_names():
    with pytest.raises(WiringError, match=r"two blocks named 'k'"):
        Diagram("d", [Gain("k", 1.0), Gain("k", 2.0)])


def test_algebraic_loop_lists_the_cycle():
    g1, g2, s = Gain("g1", 0.5), Gain("g2", 0.5), Sum("s", "++")
    c = Constant("c", 1.0)
    with pytest.raises(AlgebraicLoopError) as err:
        Diagram("d", [c, s, g1, g2], [("c.y", "s.u0"), ("s.y", "g1.u"), ("g1.y", "g2.u"), ("g2.y", "s.u1")])
    assert set(err.value.cycle) == {"s", "g1", "g2"}
    assert "s" in str(err.value) and "g1" in str(err.value) and "g2" in str(err.value)


def test_loop_through_a_delay_is_fine():
    c, s, g, z = Constant("c", 1.0), Sum("s", "+-"), Gain("g", 0.5), Delay("z", 1)
    d = Diagram("d", [c, s, g, z], [("c.y", "s.u0"), ("s.y", "g.u"), ("g.y", "z.u"), ("z.y", "s.u1")],
                outputs={"y": "g.y"})
    assert [lf.path for lf in d.schedule.leaves].index("s") < [lf.path for lf in d.schedule.leaves].index("g")


def test_rate_must_be_multiple_of_base():
    with pytest.raises(RateError, match=r"block 'k' has period 0.05 s"):
        Diagram("d", [Constant("c", 1.0), Gain("k", 1.0, dt=0.05)], [("c.y", "k.u")])


def test_nesting_does_not_invent_algebraic_loop():
    # inner: a = Gain (feedthrough) on input x, and an independent Integrator from input w.
    inner = Diagram("inner", [Gain("g", 2.0), Integrator("i", out_unit="1")], inputs={"x": "g.u", "w": "i.u"},
                    outputs={"gy": "g.y", "iy": "i.y"})
    assert inner.feedthrough  # x reaches gy directly
    # outer feeds inner.iy back into inner.x: no real loop since iy comes from the integrator
    src = Constant("c", 1.0)
    outer = Diagram("outer", [inner, src], [("inner.iy", "inner.x"), ("c.y", "inner.w")],
                    outputs={"y": "inner.gy"})
    assert {lf.path for lf in outer.schedule.leaves} == {"inner/g", "inner/i", "c"}


def test_block_rejects_bad_names_and_ports():
    with pytest.raises(WiringError, match="must be non-empty"):
        Block("a.b")
    with pytest.raises(WiringError, match="declares input 'u' twice"):
        Block("b", inputs=[Port("u"), Port("u")])
    with pytest.raises(ValueError, match="identifier"):
        Port("not a name")


def test_pi_bool_port_type_checked():
    pi = PI("pi", 1.0, 1.0)
    with pytest.raises(WiringError, match="type mismatch"):
        Diagram("d", [Constant("c", 1.0), pi, Gain("k", 1.0)], [("c.y", "pi.e"), ("pi.saturated", "k.u")])


def test_missing_external_input_value():
    from magctl.core import simulate

    d = Diagram("d", [Gain("k", 2.0)], inputs={"r": "k.u"}, outputs={"y": "k.y"})
    with pytest.raises(WiringError, match=r"d\.r needs a value"):
        simulate(d, 3)
    res = simulate(d, 3, inputs={"r": 1.5})
    assert np.allclose(res["y"], 3.0)


def test_exported_input_may_drive_several_ports():
    from magctl.core import simulate

    d = Diagram("fan", [Gain("a", 2.0), Gain("b", 3.0)], inputs={"x": ["a.u", "b.u"]},
                outputs={"ya": "a.y", "yb": "b.y"})
    res = simulate(d, 2, inputs={"x": 1.0})
    assert np.allclose(res["ya"], 2.0) and np.allclose(res["yb"], 3.0)
    with pytest.raises(WiringError, match=r"unit mismatch: fan\.x"):
        Diagram("fan", [Gain("a", 2.0), Gain("b", 3.0, in_unit="m")], inputs={"x": ["a.u", "b.u"]})
