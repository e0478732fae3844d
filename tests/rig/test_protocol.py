"""Wire format and limits, without sockets."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magctl.plant.coils import CoilActuator, load_coils
from magctl.rig import protocol as P
from magctl.rig.interface import CoilMap, Command, CommandRejected, Observation, RigLimits

finite = st.floats(allow_nan=False, allow_infinity=False, width=64)


def req(**kw) -> bytes:
    return json.dumps(P.request(kw.pop("op", "hello"), kw.pop("id", 1), **kw)).encode()


@pytest.mark.parametrize("raw, code", [
    (b"\xff\xfe\x00garbage", P.BAD_JSON),
    (b'{"protocol": "magctl-rig", "version": 2, "id": 1, "op": "re', P.BAD_JSON),  # truncated
    (b"[1, 2, 3]", P.BAD_JSON),
    (b'{"protocol": "magctl-rig", "version": 2, "id": 1, "op": "write", "cmd": {"b_osc_T": NaN}}', P.BAD_JSON),
    (b'{"protocol": "magctl-rig", "version": 2, "id": 1, "op": "write", "cmd": {"b_osc_T": Infinity}}', P.BAD_JSON),
    (b'{"protocol": "magctl-rig", "version": 1, "id": 1, "op": "read"}', P.BAD_VERSION),
    (b'{"protocol": "other", "version": 2, "id": 1, "op": "read"}', P.BAD_REQUEST),
    (b'{"protocol": "magctl-rig", "version": 2, "id": "x", "op": "read"}', P.BAD_REQUEST),
    (b'{"protocol": "magctl-rig", "version": 2, "id": 3, "op": "launch"}', P.BAD_REQUEST),
    (b" " * (P.MAX_MESSAGE_BYTES + 1), P.TOO_LARGE),
])
def test_bad_requests_are_refused_with_their_code(raw, code):
    with pytest.raises(P.ProtocolError) as err:
        P.parse_request(raw)
    assert err.value.code == code


@pytest.mark.parametrize("cmd, code", [
    ({"b_static_T": [0.0], "b_osc_T": 0.0, "freq_Hz": 0.0}, P.BAD_COMMAND),
    ({"b_static_T": [0.0, "1"], "b_osc_T": 0.0, "freq_Hz": 0.0}, P.BAD_COMMAND),
    ({"b_static_T": [0.0, 0.0], "b_osc_T": True, "freq_Hz": 0.0}, P.BAD_COMMAND),
    ({"b_static_T": [0.0, 0.0], "b_osc_T": 0.0}, P.BAD_REQUEST),
    ([0.0, 0.0], P.BAD_REQUEST),
    ({"b_static_T": [0.0, 1e309], "b_osc_T": 0.0, "freq_Hz": 0.0}, P.BAD_COMMAND),  # json turns 1e309 into inf
])
def test_malformed_commands_are_refused(cmd, code):
    doc = json.loads(json.dumps(cmd))
    with pytest.raises(P.ProtocolError) as err:
        P.command_from_wire(doc)
    assert err.value.code == code


def test_encode_refuses_nan():
    with pytest.raises(ValueError):
        P.encode({"x": float("nan")})


@given(st.lists(finite, min_size=2, max_size=2), finite, finite)
def test_command_round_trips_bit_for_bit(bs, bo, fr):
    cmd = Command(np.array(bs), bo, fr)
    back = P.command_from_wire(P.decode(P.encode(P.command_to_wire(cmd))))
    assert back.b_static.tobytes() == cmd.b_static.tobytes()
    assert (back.b_osc, back.freq) == (cmd.b_osc, cmd.freq)


@given(st.lists(finite, min_size=2, max_size=2), finite, st.integers(0, 3), st.booleans())
def test_observation_round_trips_bit_for_bit(r, h, n, lost):
    rng = np.random.default_rng(n)
    obs = Observation(t=h, frame=n, robot_est=np.array(r), heading_est=h, spheres_est=rng.normal(size=(n, 2)),
                      lost=lost, currents=rng.normal(size=6))
    back = P.observation_from_wire(P.decode(P.encode(P.observation_to_wire(obs))))
    for a, b in ((obs.robot_est, back.robot_est), (obs.spheres_est, back.spheres_est),
                 (obs.currents, back.currents)):
        assert a.shape == b.shape and a.tobytes() == b.tobytes()
    assert (back.t, back.frame, back.heading_est, back.lost) == (obs.t, obs.frame, obs.heading_est, obs.lost)


# --- limits -------------------------------------------------------------------------------------------
# A hand-made map: one coil pair per axis, each coil giving 1 mT/A, 2 A amplifiers. The pair delivers
# 4 mT, so with a 6 mT field limit the current limit binds first.
K = 1e-3
PAIR_PINV = np.zeros((6, 4))
PAIR_PINV[0:2, 0] = PAIR_PINV[2:4, 1] = PAIR_PINV[4:6, 2] = 1.0 / (2 * K)
LIM = RigLimits(b_static_max=6e-3, b_osc_max=6e-3, freq_max=200.0, coils=CoilMap(PAIR_PINV, np.full(6, 2.0)))
MU0 = 4e-7 * np.pi


def test_coil_map_splits_each_axis_over_its_pair():
    cur = LIM.currents(Command(np.array([2e-3, -1e-3]), 3e-3, 10.0))
    # B = 2 k I per pair with k = 1 mT/A; the amplifier's peak is |static| + oscillation amplitude
    np.testing.assert_allclose(cur, [1.0, 1.0, 0.5, 0.5, 1.5, 1.5])


def thick_coil_on_axis(turns, length, r_in, r_out, z):
    """Closed-form on-axis field per ampere (T/A) of a uniform thick solenoid, ``z`` from its centre."""
    def term(zz):
        return zz * np.log((r_out + np.hypot(r_out, zz)) / (r_in + np.hypot(r_in, zz)))
    return MU0 * turns / (2 * length * (r_out - r_in)) * (term(z + length / 2) - term(z - length / 2))


def test_the_rig_limits_use_the_actuator_of_models_coils():
    """The server's map is the actuator's: for B_x each x coil carries B / (2 k) with k the closed-form
    field of one winding of models/coils.toml at the workspace centre (magpylib's filaments: within 2 %)."""
    coils = load_coils()
    lim = RigLimits.from_params()
    xp = next(c for c in coils.coils if c.name == "xp")
    k = thick_coil_on_axis(xp.turns, xp.length, xp.radius - xp.depth / 2, xp.radius + xp.depth / 2,
                           np.linalg.norm(xp.position))
    i = lim.coils.static_currents(np.array([[1e-3, 0.0]]))[0]
    names = lim.coils.names
    np.testing.assert_allclose(abs(i[names.index("xp")]), 1e-3 / (2 * k), rtol=0.02)
    np.testing.assert_allclose(i[names.index("xp")], -i[names.index("xn")], rtol=1e-9)
    np.testing.assert_allclose(lim.coils.current_limit, coils.current_limit)
    # the map agrees with the actuator block: an accepted command is delivered unsaturated
    act = CoilActuator("coils", coils)
    cmd = Command(np.array([2.5e-3, -1.0e-3]), 1.45e-3, 20.0)
    lim.check(cmd)
    b, bo, sat = act.deliver(cmd.b_static, cmd.b_osc, cmd.freq)
    np.testing.assert_allclose(b[0], cmd.b_static, rtol=1e-9)
    assert not sat[0]
    # just above a coil's rating: rejected by the server, saturated by the actuator
    scale = 1.001 * lim.coils.static_headroom(np.array([1e-3, 0.0]))
    big = Command(np.array([scale * 1e-3, 0.0]), 0.0, 0.0)
    with pytest.raises(CommandRejected, match="coil x. current"):
        RigLimits(1.0, 1.0, 200.0, lim.coils).check(big)
    assert act.deliver(big.b_static, 0.0, 0.0)[2][0]


@pytest.mark.parametrize("cmd, words", [
    (Command(np.array([7e-3, 0.0]), 0.0, 0.0), "b_static"),
    (Command(np.array([0.0, 0.0]), -1e-3, 0.0), "b_osc"),
    (Command(np.array([0.0, 0.0]), 0.0, 250.0), "freq"),
    (Command(np.array([5e-3, 0.0]), 0.0, 0.0), "current"),  # 2.5 A > 2 A
    (Command(np.array([np.nan, 0.0]), 0.0, 0.0), "finite"),
    (Command(np.array([0.0, 0.0]), np.inf, 0.0), "finite"),
])
def test_limit_violations_are_named(cmd, words):
    with pytest.raises(CommandRejected, match=words):
        LIM.check(cmd)


@settings(max_examples=200)
@given(st.lists(st.floats(-1.0, 1.0), min_size=2, max_size=2), st.floats(-1.0, 1.0), st.floats(-1e3, 1e3))
def test_clipped_commands_always_pass_the_check(bs, bo, fr):
    clipped = LIM.clip(Command(np.array(bs), bo, fr))
    LIM.check(clipped)
    # direction of the in-plane field is kept
    if np.hypot(*bs) > 1e-9 and np.hypot(*clipped.b_static) > 0:
        cos = np.dot(bs, clipped.b_static) / np.hypot(*bs) / np.hypot(*clipped.b_static)
        assert cos > 1 - 1e-9


def test_command_from_values_checks_shape_and_finiteness():
    with pytest.raises(CommandRejected, match="2 elements"):
        Command.from_values([1.0, 2.0, 3.0], 0.0, 0.0)
    with pytest.raises(CommandRejected, match="not finite"):
        Command.from_values([1.0, 2.0], float("nan"), 0.0)
