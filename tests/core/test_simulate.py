"""Simulation: agreement with python-control, batch independence, multi-rate, NaN reports."""

import re
from concurrent.futures import ProcessPoolExecutor

import control
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magctl.core import (
    Block,
    Constant,
    Delay,
    Diagram,
    Gain,
    GaussianNoise,
    Integrator,
    NonFiniteSignalError,
    Port,
    StateSpace,
    Sum,
    simulate,
)

DT = 1 / 30


def random_stable_ss(rng, n, m, p):
    A = rng.standard_normal((n, n))
    A *= rng.uniform(0.2, 0.9) / max(1e-9, np.abs(np.linalg.eigvals(A)).max())
    return control.ss(A, rng.standard_normal((n, m)), rng.standard_normal((p, n)),
                      rng.standard_normal((p, m)) * rng.integers(0, 2), dt=DT)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), n1=st.integers(1, 3), n2=st.integers(1, 3), k=st.floats(0.05, 0.4))
def test_random_stable_feedback_matches_forced_response(seed, n1, n2, k):
    """r → Σ → P1 → P2 → y, fed back through gain k and a one-step delay; compare with control.feedback."""
    rng = np.random.default_rng(seed)
    p1 = random_stable_ss(rng, n1, 1, 1)
    p2 = random_stable_ss(rng, n2, 1, 1)
    blocks = [
        Sum("e", "+-", shape=(1,)),
        StateSpace.from_control("p1", p1),
        StateSpace.from_control("p2", p2),
        Gain("k", k, shape=(1,)),
        Delay("z", 1, shape=(1,)),
    ]
    d = Diagram("loop", blocks,
                [("e.y", "p1.u"), ("p1.y", "p2.u"), ("p2.y", "k.u"), ("k.y", "z.u"), ("z.y", "e.u1")],
                inputs={"r": "e.u0"}, outputs={"y": "p2.y"})
    steps = 60
    r = rng.standard_normal(steps)
    res = simulate(d, steps, inputs={"r": r[:, None]})
    # independent construction in python-control
    ref_sys = control.feedback(p2 * p1, k * control.tf([1], [1, 0], dt=DT), sign=-1)
    ref = control.forced_response(ref_sys, np.arange(steps) * DT, r)
    assert np.allclose(res["y"][0, :, 0], ref.outputs, atol=1e-9, rtol=1e-9)
    # and the exported diagram reproduces the same response
    exp = control.forced_response(d.to_control(), np.arange(steps) * DT, r)
    assert np.allclose(exp.outputs, ref.outputs, atol=1e-9, rtol=1e-9)


def test_closed_loop_poles_equal_python_control():
    from magctl.core import PI

    kp, ki, d = 1.2, 0.4, 2
    blocks = [Sum("e", "+-", shape=(1,)), PI("pi", kp, ki, shape=(1,)), Integrator("plant", shape=(1,), out_unit="1"),
              Delay("cam", d, shape=(1,))]
    dia = Diagram("servo", blocks, [("e.y", "pi.e"), ("pi.u", "plant.u"), ("plant.y", "cam.u"), ("cam.y", "e.u1")],
                  inputs={"r": "e.u0"}, outputs={"p": "plant.y"})
    z = control.tf([1, 0], [1], dt=DT)
    C = kp + ki * DT / (z - 1)
    P = DT / (z - 1)
    ref = control.feedback(C * P, z ** (-d))
    got = np.sort_complex(control.poles(dia.to_control()))
    want = np.sort_complex(control.poles(ref))
    assert got.shape == want.shape
    assert np.allclose(got, want, atol=1e-8)


def noisy_walk() -> Diagram:
    noise = GaussianNoise("noise", 1.0, shape=(2,))
    integ = Integrator("walk", shape=(2,), out_unit="1")
    zero = Constant("zero", [0.0, 0.0], shape=(2,))
    return Diagram("walk", [zero, noise, integ], [("zero.y", "noise.u"), ("noise.y", "walk.u")],
                   outputs={"x": "walk.y"})


def _trial_alone(k: int) -> np.ndarray:
    return simulate(noisy_walk(), 300, batch=1, seed=11, trials=[k])["x"][0]


def test_trial_independent_of_batch_and_process():
    big = simulate(noisy_walk(), 300, batch=40, seed=11)["x"]
    alone = _trial_alone(17)
    assert np.array_equal(big[17], alone)
    # another slice of the experiment in which trial 17 sits at a different row
    mid = simulate(noisy_walk(), 300, batch=5, seed=11, trials=[30, 17, 3, 4, 5])["x"]
    assert np.array_equal(mid[1], alone)
    with ProcessPoolExecutor(max_workers=1) as pool:
        other = pool.submit(_trial_alone, 17).result()
    assert np.array_equal(other, alone)
    assert not np.array_equal(big[16], big[17])  # trials do differ


def _ziggurat_tables(n=256):
    """Doornik's layer edges for the n-layer ziggurat, r solved here so that the top layer closes."""
    import math

    from scipy.optimize import brentq

    f = lambda x: math.exp(-x * x / 2)                                    # noqa: E731
    area = lambda r: r * f(r) + math.sqrt(math.pi / 2) * math.erfc(r / math.sqrt(2))   # noqa: E731

    def edges(r):
        v, x = area(r), [area(r) / f(r), r]
        for _ in range(1, n - 1):
            level = v / x[-1] + f(x[-1]) if x[-1] > 0 else 1.0
            x.append(math.sqrt(-2 * math.log(level)) if level < 1 else 0.0)   # 0: the layers closed too early
        return x + [0.0], v

    def top_gap(r):
        x, v = edges(r)
        return x[n - 1] * (1 - f(x[n - 1])) - v

    r = brentq(top_gap, 3.0, 4.0, xtol=1e-15)
    return edges(r)[0], r


def test_the_draw_address_is_the_contract():
    """Trial k's normal i at step p: the 64-bit half (i mod 2) of Philox4x32-10 of (p, i // 2, k, block key)
    under the seed, turned into a normal by the 256-layer ziggurat (written here in plain Python from Doornik's
    description, a rejection reading the block of kind 8 + attempt)."""
    import math

    from magctl.core.philox import philox4x32
    from magctl.core.random import block_key

    x_edge, r = _ziggurat_tables()
    rejected = []

    def unit(hi, lo):
        return ((int(hi) << 32 | int(lo)) >> 11) / 2.0**53

    def words(seed, trial, path, step, c1):
        return philox4x32(*(np.uint64(v) for v in (step, c1, trial, block_key(path), seed, 0)))

    def draw(seed, trial, path, step, i):
        w = words(seed, trial, path, step, i // 2)
        hi, lo = (w[0], w[1]) if i % 2 == 0 else (w[2], w[3])
        for attempt in range(8):
            u = 2 * unit(hi, lo) - 1
            layer = int(lo) & 0xFF
            x = u * x_edge[layer]
            if abs(x) < x_edge[layer + 1]:
                return x
            rejected.append((step, i))
            e = words(seed, trial, path, step, (8 + attempt) << 28 | i)
            if layer == 0:
                while True:
                    t, y = -math.log(1 - unit(e[0], e[1])) / r, -math.log(1 - unit(e[2], e[3]))
                    if 2 * y > t * t:
                        return math.copysign(r + t, u)
                    e = philox4x32(*e, np.uint64(seed), np.uint64(0))
            fx = [math.exp(-v * v / 2) for v in (x_edge[layer], x_edge[layer + 1])]
            if fx[1] + unit(e[2], e[3]) * (fx[0] - fx[1]) < math.exp(-x * x / 2):
                return x
            hi, lo = e[0], e[1]
        return x

    steps = np.array([[draw(11, 17, "noise", p, i) for i in range(2)] for p in range(300)])
    assert rejected, "no draw of these 600 took the rejection path: pick more steps"
    x = _trial_alone(17)
    np.testing.assert_allclose(x[1:], np.cumsum(steps, axis=0)[:-1] * DT, rtol=1e-12, atol=1e-15)


def test_the_ziggurat_constants_are_the_published_ones():
    from magctl.core.philox import _ZX, ZIGGURAT_R

    x_edge, r = _ziggurat_tables()
    assert r == pytest.approx(ZIGGURAT_R, rel=1e-14)          # Marsaglia and Tsang 2000: 3.6541528853610088
    np.testing.assert_allclose(_ZX, x_edge, rtol=1e-12, atol=1e-15)


class Slow(Block):
    """Counts its own ticks; runs every third frame."""

    def __init__(self):
        super().__init__("slow", outputs=[Port("n")], dt=3 * DT, feedthrough=False)

    def initial_state(self, batch, rng=None):
        return {"n": np.zeros(batch)}

    def output(self, state, u):
        return {"n": state["n"].copy()}

    def update(self, state, u):
        return {"n": state["n"] + 1}


def test_multirate_holds_outputs_between_ticks():
    d = Diagram("m", [Slow(), Gain("g", 1.0)], [("slow.n", "g.u")], outputs={"y": "g.y"})
    y = simulate(d, 9)["y"][0]
    assert np.array_equal(y, [0, 0, 0, 1, 1, 1, 2, 2, 2])


class BadAt(Block):
    def __init__(self, step):
        super().__init__("bad", inputs=[Port("u")], outputs=[Port("y")], feedthrough=True)
        self.bad_step = step

    def initial_state(self, batch, rng=None):
        return {"k": 0}

    def output(self, state, u):
        y = u["u"].copy()
        if state["k"] == self.bad_step:
            y[1] = np.nan
        return {"y": y}

    def update(self, state, u):
        return {"k": state["k"] + 1}


def test_nan_is_reported_with_block_port_step():
    d = Diagram("n", [Constant("c", 1.0), BadAt(37), Gain("after", 1.0)],
                [("c.y", "bad.u"), ("bad.y", "after.u")], outputs={"y": "after.y"})
    with pytest.raises(NonFiniteSignalError) as err:
        simulate(d, 100, batch=3)
    e = err.value
    assert (e.step, e.source, e.consumers, e.trials) == (37, "bad.y", ["after.u"], [1])
    assert "bad.y" in str(e) and "step 37" in str(e) and "after.u" in str(e)
    assert e.partial["y"].shape == (3, 37)
    assert np.isfinite(e.partial["y"]).all()


def test_nested_diagram_equals_flat():
    inner = Diagram("inner", [Gain("g", 0.5), Integrator("i", out_unit="1")], [("g.y", "i.u")], inputs={"x": "g.u"},
                    outputs={"y": "i.y"})
    outer = Diagram("outer", [Constant("c", 2.0), inner], [("c.y", "inner.x")], outputs={"y": "inner.y"})
    flat = Diagram("flat", [Constant("c", 2.0), Gain("g", 0.5), Integrator("i", out_unit="1")],
                   [("c.y", "g.u"), ("g.y", "i.u")], outputs={"y": "i.y"})
    assert np.array_equal(simulate(outer, 20)["y"], simulate(flat, 20)["y"])
    # and a diagram steps as a block with B=1
    state = inner.initial_state(1)
    ys = []
    for _ in range(5):
        y, state = inner.step(state, {"x": np.array([2.0])})
        ys.append(float(y["y"][0]))
    assert np.allclose(ys, [0, DT, 2 * DT, 3 * DT, 4 * DT])


def test_result_unpacks_as_t_y():
    d = Diagram("d", [Constant("c", 1.0), Integrator("i", out_unit="1")], [("c.y", "i.u")], outputs={"x": "i.y"})
    t, y = simulate(d, 4, batch=2)
    assert np.allclose(t, np.arange(4) * DT)
    assert y["x"].shape == (2, 4)
    with pytest.raises(KeyError, match="no recorded signal"):
        simulate(d, 4)["nope.y"]


def test_simulate_and_diagram_step_run_the_same_schedule():
    """simulate and stepping the diagram by hand (as the rig does) give the same trajectories,
    noise and multirate holds included; Diagram.output agrees with step's outputs."""
    from magctl.testing import b1_diagram

    inner = b1_diagram()
    d = Diagram("m", [inner, Slow(), Gain("g", 1.0)], [("slow.n", "g.u")],
                outputs={"p": "b1.p", "y": "b1.y", "n": "g.y"})
    res = simulate(d, 40, batch=2, seed=3)
    st = d.initial_state(2, seed=3)
    for k in range(40):
        y = d.output(st, {})
        outs, st = d.step(st, {})
        for name in ("p", "y", "n"):
            assert np.array_equal(outs[name], res[name][:, k]), (name, k)
            assert np.array_equal(y[name], outs[name]), (name, k)
    assert st["tick"] == res.final_state["tick"] == 40


@pytest.mark.parametrize("steps, batch, seed, words", [
    (-5, 1, 0, "steps must be a whole number >= 0, got -5"),
    (2.5, 1, 0, "steps must be a whole number >= 0, got 2.5"),
    (10, 0, 0, "batch must be a whole number >= 1, got 0"),
    (10, True, 0, "batch must be a whole number >= 1, got True"),
    (10, 1, -1, "seed must be a whole number in [0, 2**64), got -1"),
])
def test_simulate_refuses_counts_it_cannot_run(steps, batch, seed, words):
    """A negative or fractional step count, an empty batch or a negative seed: one error naming it, not a run of a
    truncated length or a numpy IndexError."""
    from magctl.core import MagctlError

    d = Diagram("c", [Constant("c", 1.0), Gain("g", 2.0)], [("c.y", "g.u")], outputs={"y": "g.y"})
    with pytest.raises(MagctlError, match=re.escape(words)):
        simulate(d, steps, batch=batch, seed=seed)
    assert simulate(d, np.float64(4.0), batch=2)["y"].shape == (2, 4)      # a whole float is a count


def test_core_blocks_refuse_non_finite_gains():
    from magctl.core import PI, MagctlError

    for make, words in ((lambda: PI("c", kp=np.nan, ki=1.0), "kp=nan must be finite"),
                        (lambda: PI("c", kp=1.0, ki=np.inf), "ki=inf must be finite"),
                        (lambda: PI("c", 1.0, 1.0, limit=-1.0), "limit=-1.0 must be positive"),
                        (lambda: Gain("g", [1.0, np.nan]), "must be finite")):
        with pytest.raises(MagctlError, match=words):
            make()
