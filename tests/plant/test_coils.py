"""Coil field and the coil actuator block, against closed forms, magpylib's object API and python-control."""

from dataclasses import replace

import control
import magpylib as magpy
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magctl.core.errors import ParameterError
from magctl.plant.coils import Coil, CoilActuator, CoilSet, load_coils

MU0 = 4e-7 * np.pi
H = 1.0 / 30.0


def single_loop(turns, radius, axis=(0.0, 0.0, 1.0)):
    coil = Coil("loop", np.zeros(3), np.asarray(axis, float), turns, radius, 0.0, 0.0, 1.0, 1e-3, 1.0, 1.0)
    return CoilSet((coil,), np.zeros(3), "sine", 0.0, "test")


@settings(max_examples=20, deadline=None)
@given(turns=st.integers(1, 2000), radius=st.floats(1e-3, 0.1), current=st.floats(-5, 5))
def test_loop_centre_is_mu0_n_i_over_2a(turns, radius, current):
    b = single_loop(turns, radius).field([[0.0, 0.0, 0.0]], [current])[0]
    assert b[2] == pytest.approx(MU0 * turns * current / (2 * radius), rel=1e-9, abs=1e-15)
    assert np.hypot(b[0], b[1]) <= 1e-12 * max(abs(b[2]), 1e-12)


@settings(max_examples=20, deadline=None)
@given(z=st.floats(-0.2, 0.2), radius=st.floats(1e-3, 0.05))
def test_loop_on_axis_closed_form(z, radius):
    n, i = 300, 1.5
    b = single_loop(n, radius).field([[0.0, 0.0, z]], [i])[0]
    expected = MU0 * n * i * radius**2 / (2 * (radius**2 + z**2) ** 1.5)
    assert b[2] == pytest.approx(expected, rel=1e-9)


def test_tilted_loop_points_field_along_its_axis():
    axis = np.array([1.0, 1.0, 0.0]) / np.sqrt(2)
    b = single_loop(10, 0.01, axis).field([[0.0, 0.0, 0.0]], [1.0])[0]
    assert b / np.linalg.norm(b) == pytest.approx(axis, abs=1e-12)


def test_six_coils_match_magpylib_object_api():
    """Superposition of every filament built with magpylib's own objects, independent of our functional path."""
    cs = load_coils()
    rng = np.random.default_rng(1)
    currents = rng.uniform(-2, 2, 6)
    coll = magpy.Collection()
    for coil, cur in zip(cs.coils, currents):
        centres, diam, turns = coil.filaments()
        for c, d, t in zip(centres, diam, turns):
            coll.add(magpy.current.Circle(current=cur * t, diameter=d, position=c, orientation=coil.rotation()))
    pts = rng.uniform(-3e-3, 3e-3, (5, 3))
    ours = cs.field(pts, currents)
    ref = magpy.getB(coll, pts, sumup=True)
    assert ours == pytest.approx(np.asarray(ref).reshape(ours.shape), rel=1e-9, abs=1e-15)


def test_actuation_matrix_symmetry():
    A = load_coils().actuation_matrix()
    # opposite coils of a pair give equal and opposite field at the centre (axes point inwards)
    assert A[0, 0] == pytest.approx(-A[0, 1], rel=1e-9)
    assert A[1, 2] == pytest.approx(-A[1, 3], rel=1e-9)
    assert A[2, 4] == pytest.approx(-A[2, 5], rel=1e-9)
    # 90° rotation maps the x pair onto the y pair
    assert A[0, 0] == pytest.approx(A[1, 2], rel=1e-9)
    # in-plane coils make no B_z, vertical coils no in-plane field at the centre
    scale = np.abs(A[:3]).max()
    assert np.abs(A[2, :4]).max() < 1e-9 * scale
    assert np.abs(A[:2, 4:]).max() < 1e-9 * scale
    assert np.abs(A[0, 2:]).max() < 1e-9 * scale
    # ∂B_z/∂z: the two vertical coils contribute equally (mirror images about z = 0)
    assert A[3, 4] == pytest.approx(A[3, 5], rel=1e-6)
    assert np.linalg.matrix_rank(A) == 4


def test_field_is_uniform_over_the_workspace():
    cs = load_coils()
    cur = np.linalg.pinv(cs.actuation_matrix()) @ [2e-3, 0.0, 0.0, 0.0]
    pts = np.array([[x, y, 0.0] for x in (-2e-3, 0, 2e-3) for y in (-2e-3, 0, 2e-3)])
    b = cs.field(pts, cur)
    assert b[:, 0] == pytest.approx(2e-3, rel=0.02)  # within 2 % over ±2 mm
    assert np.abs(b[:, 1:]).max() < 0.02 * 2e-3


def step(block, state, u):
    return block.output(state, u), block.update(state, u)


def cmd(bs, bo=0.0, f=0.0, batch=1):
    return {"b_static": np.broadcast_to(np.asarray(bs, float), (batch, 2)).copy(),
            "b_osc": np.full(batch, float(bo)), "freq": np.full(batch, float(f))}


def test_command_within_limits_is_delivered():
    act = CoilActuator()
    s = act.initial_state(3)
    u = cmd([1.5e-3, -0.8e-3], 1.2e-3, 10.0, batch=3)
    for _ in range(3):
        out, s = step(act, s, u)
    assert out["b_static_delivered"] == pytest.approx(u["b_static"], rel=1e-9)
    assert out["b_osc_delivered"] == pytest.approx(u["b_osc"], rel=1e-12)
    assert not out["saturated"].any()
    assert out["currents"].shape == (3, 6)


def test_static_command_beyond_current_limit_saturates_and_keeps_direction():
    act = CoilActuator()
    s = act.initial_state(1)
    u = cmd([10e-3, 10e-3])
    for _ in range(3):
        out, s = step(act, s, u)
    assert out["saturated"].all()
    b = out["b_static_delivered"][0]
    assert np.arctan2(b[1], b[0]) == pytest.approx(np.pi / 4, abs=1e-9)
    assert np.abs(out["currents"]).max() == pytest.approx(3.0, rel=1e-6)  # coils.toml current_limit_A


def test_fast_oscillation_is_voltage_limited_like_an_rl_coil():
    cs = load_coils()
    act = CoilActuator(coils=cs)
    A = cs.actuation_matrix()
    vert = cs.coils[4]
    tesla_per_amp = abs(A[2, 4]) + abs(A[2, 5])  # both vertical coils carry the same current magnitude
    for f in (50.0, 400.0, 1000.0):
        out, _ = step(act, act.initial_state(1), cmd([0.0, 0.0], 5e-3, f))
        z = np.hypot(vert.resistance, 2 * np.pi * f * vert.inductance)
        limit = min(vert.voltage_limit / z, vert.current_limit) * tesla_per_amp
        assert out["b_osc_delivered"][0] == pytest.approx(min(5e-3, limit), rel=1e-9)
        assert out["saturated"][0] == (limit < 5e-3)


def test_rl_dynamics_match_python_control_zoh():
    base = load_coils()
    slow = CoilSet(tuple(replace(c, inductance=c.resistance * 0.02) for c in base.coils), base.centre,
                   base.waveform, 0.0, "slow")  # τ = 20 ms, comparable to the frame
    act = CoilActuator(coils=slow)
    n = 6
    u = cmd([1e-3, 0.0])
    i_cmd = u["b_static"] @ act.pinv[:, :2].T
    s = act.initial_state(1)
    traj = []
    for _ in range(n):
        traj.append(s["i"][0].copy())
        _, s = step(act, s, u)
    c = slow.coils[0]
    sys = control.c2d(control.ss([[-c.resistance / c.inductance]], [[1.0 / c.inductance]], [[1.0]], [[0.0]]),
                      H, method="zoh")
    v = c.resistance * i_cmd[0, 0]  # the amplifier's feed-forward voltage
    resp = control.forced_response(sys, U=np.full(n, v), X0=0.0)
    assert np.array(traj)[:, 0] == pytest.approx(resp.outputs, rel=1e-9, abs=1e-12)


def test_outputs_are_not_mutated_by_update():
    act = CoilActuator()
    s = act.initial_state(2)
    u = cmd([1e-3, 0.0], 1e-3, 5.0, batch=2)
    out, s = step(act, s, u)
    snap = {k: v.copy() for k, v in out.items()}
    step(act, s, cmd([0.0, 1e-3], 0.0, 0.0, batch=2))
    for k in out:
        assert np.array_equal(out[k], snap[k])


def _write_coils(tmp_path, monkeypatch, mutate):
    text = load_coils().source
    src = open(text).read()
    (tmp_path / "coils.toml").write_text(mutate(src))
    monkeypatch.setenv("MAGCTL_MODELS", str(tmp_path))


def test_malformed_coil_file_names_field_and_file(tmp_path, monkeypatch):
    _write_coils(tmp_path, monkeypatch,
                 lambda s: s.replace("resistance_ohm = { value = 1.7", "resistance_ohm = { value = -1.7", 1))
    with pytest.raises(ParameterError, match=r"coils\.toml.*'resistance'"):
        load_coils()


def test_coil_file_with_bad_axis_fails(tmp_path, monkeypatch):
    _write_coils(tmp_path, monkeypatch, lambda s: s.replace("value = [-1.0, 0.0, 0.0]", "value = [-1.0, 0.0]", 1))
    with pytest.raises(ParameterError, match=r"coils\.toml.*'axis'"):
        load_coils()


def test_coil_file_missing_key_fails(tmp_path, monkeypatch):
    def drop(s):
        lines = s.splitlines()
        i = next(k for k, ln in enumerate(lines) if ln.startswith("inductance_mH"))
        return "\n".join(lines[:i] + lines[i + 1:])
    _write_coils(tmp_path, monkeypatch, drop)
    with pytest.raises(ParameterError, match=r"coils\.toml.*inductance"):
        load_coils()


def test_coil_file_missing_source_fails(tmp_path, monkeypatch):
    _write_coils(tmp_path, monkeypatch, lambda s: s.replace(
        'turns_count = { value = 400, source = "assumed: 400 turns fill the 20 × 10 mm winding with 0.7 mm wire" }',
        "turns_count = { value = 400 }", 1))
    with pytest.raises(ParameterError, match=r"coils\.toml.*turns_count.*source"):
        load_coils()


def test_the_rig_checks_commands_with_the_actuators_own_allocation():
    """CoilMap (the rig's limit check) and CoilActuator share one CoilAllocation: same currents, same numbers."""
    from magctl.rig.interface import CoilMap

    act, cmap = CoilActuator("coils"), CoilMap.from_coils()
    rng = np.random.default_rng(3)
    b = 1e-3 * rng.standard_normal((50, 2))
    bo = 1e-3 * rng.random(50)
    np.testing.assert_array_equal(cmap.static_currents(b), act.allocation.static_currents(b))
    np.testing.assert_array_equal(cmap.osc_currents(bo), act.allocation.osc_currents(bo))
    # and it is i = A⁺ [b_x, b_y, 0, G]: solve the allocation's defining least-norm problem independently
    full = np.column_stack([b, np.zeros(50), np.full(50, act.coils.clamp_gradient)])
    ref = np.linalg.lstsq(act.A, full.T, rcond=None)[0].T
    np.testing.assert_allclose(cmap.static_currents(b), ref, rtol=1e-9, atol=1e-12)
