"""The serve-sim subprocess: watchdog, hostile messages, server-side limits, losing the server."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest
import zmq
from rig_helpers import magctl_cmd

from magctl.config import load_model
from magctl.rig import protocol as P
from magctl.rig.client import RigClient
from magctl.rig.interface import Command, Lifecycle, RigConnectionError, RigError

PARAMS = load_model("rig")
PERIOD = 1.0 / PARAMS.runtime.rate
WATCHDOG = PARAMS.watchdog.timeout
ROOT = Path(__file__).resolve().parents[2]


class Raw:
    """A bare REQ socket speaking to the server byte for byte."""

    def __init__(self, address):
        self.ctx = zmq.Context.instance()
        self.sock = self.ctx.socket(zmq.REQ)
        self.sock.setsockopt(zmq.LINGER, 0)
        self.sock.setsockopt(zmq.RCVTIMEO, 3000)
        self.sock.connect(address)
        self.id = 0
        self.session = None

    def send_raw(self, raw: bytes) -> dict:
        self.sock.send(raw)
        return json.loads(self.sock.recv())

    def op(self, op, **kw) -> dict:
        self.id += 1
        if self.session is not None:
            kw.setdefault("session", self.session)
        reply = self.send_raw(json.dumps(P.request(op, self.id, **kw)).encode())
        if op == "configure" and reply.get("ok"):
            self.session = reply["session"]
        if op == "deactivate" and reply.get("ok"):
            self.session = None
        return reply

    def close(self):
        self.sock.close(0)


@pytest.fixture
def raw(server):
    r = Raw(server.address)
    assert r.op("configure", reset=True)["ok"]
    yield r
    r.op("deactivate")
    r.close()


def moving():
    return {"b_static_T": [3e-3, 0.0], "b_osc_T": 3e-3, "freq_Hz": 50.0}


def test_watchdog_zeroes_the_coils_within_100_ms_plus_one_frame(raw):
    """The module's server runs in lock-step: each read is one frame of simulated time, so the bound is
    checked exactly (the real-time watchdog thread is tested in test_safety.py)."""
    assert raw.op("activate")["ok"]
    trips = raw.op("status")["watchdog_trips"]
    reply = raw.op("write", cmd=moving())
    assert reply["ok"] and max(reply["currents_A"]) > 0
    t_cmd = raw.op("status")["frame"] * PERIOD
    # go silent for commands; only watch, one frame per read
    for _ in range(10):
        t = raw.op("read")["obs"]["t_s"]
        st = raw.op("status")
        if st["coils_zero"]:
            break
    assert st["coils_zero"] and WATCHDOG < t - t_cmd <= WATCHDOG + PERIOD + 1e-12
    assert st["watchdog_trips"] == trips + 1
    assert WATCHDOG < st["watchdog_tripped_after_s"] <= WATCHDOG + PERIOD + 1e-12
    assert st["state"] == "inactive" and "watchdog" in st["last_error"]
    # the rig stays off until reactivated explicitly
    r = raw.op("write", cmd=moving())
    assert not r["ok"] and r["error"]["code"] == P.BAD_STATE
    # the coil currents decay with τ = L/R ≈ 2 ms (models/coils.toml): a frame average of the first
    # zeroed frame still holds ~5 % of the current, the ones after it nothing measurable
    for _ in range(3):
        obs = raw.op("read")["obs"]
    assert all(abs(c) < 1e-6 for c in obs["currents_A"])


@pytest.mark.parametrize("payload, code", [
    (b"\x00\xffgarbage\x13", P.BAD_JSON),
    (b'{"protocol": "magctl-rig", "version": 2, "id": 7, "op": "wri', P.BAD_JSON),
    (b"x" * (P.MAX_MESSAGE_BYTES + 1000), P.TOO_LARGE),
    (b'{"protocol": "magctl-rig", "version": 99, "id": 7, "op": "write"}', P.BAD_VERSION),
    (b'{"protocol": "magctl-rig", "version": 2, "id": 7, "op": "write", '
     b'"cmd": {"b_static_T": [NaN, 0], "b_osc_T": 0, "freq_Hz": 0}}', P.BAD_JSON),
    (json.dumps(P.request("write", 7, session="SESSION",
                          cmd={"b_static_T": [0.005, 0.0], "b_osc_T": 0.0, "freq_Hz": 1e4})).encode(), P.BAD_COMMAND),
    (json.dumps(P.request("write", 7, session="SESSION",
                          cmd={"b_static_T": [0.0, 0.0], "b_osc_T": 0.05, "freq_Hz": 10})).encode(), P.BAD_COMMAND),
    # a valid command from a client that never configured: refused, named
    (json.dumps(P.request("write", 7, cmd={"b_static_T": [2e-3, 0.0], "b_osc_T": 1e-3, "freq_Hz": 10})).encode(),
     P.NOT_OWNER),
    (b'{"protocol": "magctl-rig", "version": 2, "id": 1e400, "op": "read"}', P.BAD_JSON),
    (b'{"protocol": "magctl-rig", "version": true, "id": 7, "op": "read"}', P.BAD_VERSION),
    (b'{"protocol": "magctl-rig", "version": 2.0, "id": 7, "op": "read"}', P.BAD_VERSION),
    (b'{"protocol": "magctl-rig", "version": 2, "id": ' + b"9" * 5000 + b', "op": "read"}', P.BAD_JSON),
    (b'{"protocol": "magctl-rig", "version": 2, "id": 99999999999999999999, "op": "read"}', P.BAD_REQUEST),
])
def test_hostile_messages_get_errors_and_are_never_applied(raw, payload, code):
    assert raw.op("activate")["ok"]
    reply = raw.send_raw(payload.replace(b'"SESSION"', json.dumps(raw.session).encode()))
    assert reply["ok"] is False and reply["error"]["code"] == code and reply["error"]["message"]
    # nothing was applied, and the server keeps serving
    st = raw.op("status")
    assert st["ok"] and st["coils_zero"]
    assert raw.op("write", cmd=moving())["ok"]
    assert raw.op("hello")["ok"]


def test_server_enforces_current_limits_whatever_the_client_sends(start_server, tmp_path):
    """In-plane coils rated 1 A instead of 3 A (models/coils.toml): a 2 mT command passes the 3 mT
    field limit but needs ~1.75 A in the x coils, so the server refuses it."""
    for f in (ROOT / "models").iterdir():  # the plant reads the other parameter files from the same folder
        if f.is_file():
            (tmp_path / f.name).write_bytes(f.read_bytes())
    text = (ROOT / "models" / "coils.toml").read_text()
    assert text.count("current_limit_A = { value = 3.0,") == 4
    (tmp_path / "coils.toml").write_text(text.replace("current_limit_A = { value = 3.0,",
                                                      "current_limit_A = { value = 1.0,"))
    srv = start_server("--plant", "standin", env={"MAGCTL_MODELS": str(tmp_path)})
    raw = Raw(srv.address)
    assert raw.op("configure")["ok"] and raw.op("activate")["ok"]
    hello = raw.op("hello")["limits"]
    assert hello["current_max_A"] == 1.0 and hello["coil_current_limit_A"] == [1.0, 1.0, 1.0, 1.0, 2.0, 2.0]
    reply = raw.op("write", cmd={"b_static_T": [2e-3, 0.0], "b_osc_T": 0.0, "freq_Hz": 0.0})
    assert not reply["ok"] and reply["error"]["code"] == P.BAD_COMMAND
    assert "coil x" in reply["error"]["message"] and "current" in reply["error"]["message"]
    assert raw.op("status")["coils_zero"]
    ok = raw.op("write", cmd={"b_static_T": [1e-3, 0.0], "b_osc_T": 0.0, "freq_Hz": 0.0})
    # each x coil carries B / (2 k), k = 0.58 mT/A the closed-form on-axis field of one winding at
    # 45 mm (400 turns, radii 10-20 mm, 20 mm long; see test_protocol.thick_coil_on_axis)
    assert ok["ok"] and max(ok["currents_A"]) == pytest.approx(1e-3 / (2 * 0.5788e-3), rel=0.02)
    raw.close()


def test_killing_the_server_stops_the_client_with_a_clear_error(start_server):
    srv = start_server("--lockstep", "--plant", "standin")
    # a timeout long enough for a loaded machine to answer the set-up; after the kill the read ends on it, not
    # in a hang
    rig = RigClient(srv.address, timeout=2.0)
    rig.configure()
    rig.activate()
    rig.write(Command(np.array([3e-3, 0.0]), 3e-3, 50.0))
    rig.read()
    srv.kill()
    with pytest.raises(RigConnectionError, match="did not answer 'read' within 2000 ms"):
        rig.read()
    # the client could not zero the coils itself: it says so and refuses to go on
    assert rig.state is Lifecycle.ERROR and "zeroing" in rig.last_error
    with pytest.raises(RigError):
        rig.write(Command.zero())
    rig.close()


def test_client_refuses_a_server_of_another_protocol_version():
    """A stand-alone REP socket answering as a version-3 server."""
    import threading

    ctx = zmq.Context.instance()
    rep = ctx.socket(zmq.REP)
    port = rep.bind_to_random_port("tcp://127.0.0.1")

    def serve_once():
        req = json.loads(rep.recv())
        rep.send(json.dumps({"protocol": "magctl-rig", "version": 3, "id": req["id"], "ok": True}).encode())

    t = threading.Thread(target=serve_once)
    t.start()
    rig = RigClient(f"tcp://127.0.0.1:{port}", timeout=2.0)
    with pytest.raises(RigError, match="version 3"):
        rig.configure()
    t.join()
    rig.close()
    rep.close(0)


@pytest.mark.parametrize("plant", ["physics", "standin"])
def test_serve_sim_names_its_plant_and_scene(start_server, plant):
    """``--plant`` picks the plant behind the server (physics by default); ``hello`` reports it and the scene."""
    srv = start_server(*([] if plant == "physics" else ["--plant", plant]), "--robot-um", "1500", "1000")
    client = RigClient(srv.address)
    hello = client.call("hello")
    assert hello["scene"]["plant"] == plant
    assert hello["scene"]["robot_um"] == [1500.0, 1000.0] and hello["scene"]["spheres_um"] == [[2500.0, 1000.0]]
    client.configure()
    obs = client.read()
    assert not obs.lost and np.hypot(*(obs.robot_est - [1.5e-3, 1.0e-3])) < 7.5e-6
    client.close()


def test_serve_sim_refuses_a_scene_outside_the_camera_field():
    proc = subprocess.run(magctl_cmd("rig", "serve-sim", "--bind", "tcp://127.0.0.1:1", "--robot-um", "-200", "500"),
                          cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "outside the camera's field of view" in proc.stderr


def test_a_port_in_use_is_the_one_error_that_stops_serve_sim(server, capsys):
    from magctl.cli import main

    code = main(["rig", "serve-sim", "--bind", server.address, "--plant", "standin"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and f"cannot serve on {server.address}" in err[0]
    assert Raw(server.address).op("hello")["ok"]  # the running server is untouched
