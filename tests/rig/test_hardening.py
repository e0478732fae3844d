"""The rig server against the holes of an independent probe: takeover floods, binding beyond loopback,
``--allow`` by network and host name, CURVE keys reloaded while serving, honest reply counters, onlookers in
lock-step, and a not-owner message that says how to take over. Each test runs a real ``serve-sim``."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from pathlib import Path

import pytest
import zmq
from rig_helpers import ROOT, ServerProcess, free_port, magctl_cmd
from test_server import Raw, moving

from magctl.cli import main
from magctl.config import load_model
from magctl.rig import protocol as P
from magctl.rig.client import RigClient, RigNotOwner
from magctl.rig.interface import Command, Lifecycle, RigConnectionError, RigError
from magctl.rig.server import (
    RigServer,
    ServerSetupError,
    address_allowed,
    endpoint_is_local,
    generate_keys,
    parse_allow,
)

PARAMS = load_model("rig")
PERIOD = 1.0 / PARAMS.runtime.rate
WATCHDOG = PARAMS.watchdog.timeout


def stop_and_read_stderr(srv: ServerProcess) -> list[str]:
    """SIGTERM the server (it exits through its own clean-up) and return its stderr lines."""
    srv.kill(sig=signal.SIGTERM)
    return srv.proc.stderr.read().decode().splitlines()


def wait_until(check, timeout: float = 15.0, every: float = 0.1) -> bool:
    """Poll ``check()`` until it is true (a hang guard, not a timing assertion)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if check():
            return True
        time.sleep(every)
    return False


# --- 1. takeovers ----------------------------------------------------------------------------------------
def _models_with(tmp_path, old: str, new: str) -> Path:
    folder = tmp_path / "models"
    folder.mkdir()
    for f in (ROOT / "models").glob("*.toml"):
        (folder / f.name).write_text(f.read_text())
    text = (folder / "rig.toml").read_text()
    assert text.count(old) == 1
    (folder / "rig.toml").write_text(text.replace(old, new))
    return folder


@pytest.mark.parametrize("limited", [True, False], ids=["rate-limited", "no-rate-limit"])
def test_a_takeover_flood_cannot_flood_stderr(start_server, tmp_path, limited):
    """One client sending takeovers as fast as it can. With the shipped takeover interval, until three were
    accepted (two intervals): the rest get not-owner saying why. With the interval set to 0 (every takeover
    accepted), 3000 takeovers: their log lines still go through the one-line-a-second limit. Either way the
    server's stderr gets at most a line a second — counted over the window from the first takeover to the
    server's exit, the lines held back summed up in a later line. (Before: every takeover was accepted and
    logged, a line each; the test's unread pipe filled up and blocked the server.)"""
    env = None if limited else {"MAGCTL_MODELS": str(_models_with(tmp_path, "takeover_interval_s = { value = 1.0,",
                                                                  "takeover_interval_s = { value = 0.0,"))}
    srv = start_server("--lockstep", "--plant", "standin", env=env)
    owner, attacker = Raw(srv.address), Raw(srv.address)
    assert owner.op("configure")["ok"] and owner.op("activate")["ok"] and owner.op("write", cmd=moving())["ok"]
    accepted = refused = 0
    t0 = time.monotonic()
    while (accepted < 3 if limited else accepted + refused < 3000) and accepted + refused < 50_000:
        attacker.session = None  # a fresh takeover every time, never a renewal of its own session
        r = attacker.op("configure", takeover=True)
        if r["ok"]:
            assert r["took_over"]
            accepted += 1
        else:
            assert r["error"]["code"] == P.NOT_OWNER and "takeover refused" in r["error"]["message"]
            refused += 1
    flood = time.monotonic() - t0
    st = owner.op("status")
    assert st["takeovers"] == accepted and st["takeovers_refused"] == refused
    if limited:
        assert accepted == 3 and refused > 0 and flood >= 2 * PARAMS.session.takeover_interval
    else:
        assert accepted == 3000 and refused == 0
    owner.close()
    attacker.close()
    lines = stop_and_read_stderr(srv)
    window = time.monotonic() - t0
    # lines at least a second apart within the window (the first at its start), plus the exit line
    assert 1 <= len(lines) <= window + 2, (window, lines)
    assert any("takeover" in x and "more since the last line" in x for x in lines)


# --- 2. binding beyond loopback ----------------------------------------------------------------------------
@pytest.mark.parametrize("endpoint, local", [
    ("tcp://127.0.0.1:5555", True), ("tcp://127.3.2.1:5555", True), ("tcp://localhost:5555", True),
    ("tcp://[::1]:5555", True), ("tcp://[::ffff:127.0.0.1]:5555", True), ("ipc:///tmp/rig.ipc", True),
    ("inproc://rig", True), ("tcp://0.0.0.0:5555", False), ("tcp://*:5555", False), ("tcp://[::]:5555", False),
    ("tcp://192.168.1.20:5555", False), ("tcp://eth0:5555", False), ("tcp://lab-pc.example:5555", False),
    ("udp://127.0.0.1:5555", False), ("127.0.0.1:5555", False),
])
def test_which_endpoints_are_local(endpoint, local):
    assert endpoint_is_local(endpoint) is local


def _server(bind, **kw):
    from magctl.rig.interface import RigLimits

    return RigServer(lambda: None, bind, RigLimits.from_params(PARAMS), WATCHDOG, PERIOD, **kw)


def test_the_server_refuses_to_bind_beyond_loopback_without_curve_unless_insecure(tmp_path):
    with pytest.raises(ServerSetupError, match="refusing to bind tcp://0.0.0.0:1 without CURVE.*--insecure"):
        _server("tcp://0.0.0.0:1")
    _server("tcp://0.0.0.0:1", insecure=True)
    _server("tcp://0.0.0.0:1", curve_secret=tmp_path / "s.key_secret", curve_clients=tmp_path)  # CURVE: fine
    _server("ipc:///tmp/magctl-rig.ipc")


def test_serve_sim_beyond_loopback_is_refused_and_insecure_warns_in_one_line(start_server, capsys):
    port = free_port()
    code = main(["rig", "serve-sim", "--plant", "standin", "--bind", f"tcp://0.0.0.0:{port}"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "without CURVE" in err[0] and "--insecure" in err[0]
    # the same with --insecure serves, after one warning line; a client on loopback reaches it
    proc = subprocess.Popen(magctl_cmd("rig", "serve-sim", "--plant", "standin", "--lockstep", "--insecure",
                                       "--bind", f"tcp://0.0.0.0:{port}"),
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        assert json.loads(proc.stdout.readline())["ready"]
        client = RigClient(f"tcp://127.0.0.1:{port}", timeout=2.0)
        assert client.call("hello")["security"] == "null"
        client.close()
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=10)
    err = proc.stderr.read().decode().splitlines()
    assert len(err) == 1 and "warning" in err[0] and "without CURVE" in err[0] and "in clear" in err[0], err


def test_serve_sim_on_an_ipc_endpoint_needs_no_flag(tmp_path):
    sock = tmp_path / "rig.ipc"
    proc = subprocess.Popen(magctl_cmd("rig", "serve-sim", "--plant", "standin", "--lockstep",
                                       "--bind", f"ipc://{sock}"),
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        assert json.loads(proc.stdout.readline())["ready"]
        client = RigClient(f"ipc://{sock}", timeout=2.0)
        assert client.call("hello")["ok"]
        client.close()
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=10)
    assert proc.stderr.read() == b""


# --- 3. --allow ------------------------------------------------------------------------------------------
def test_allow_entries_are_addresses_networks_and_host_names():
    nets = parse_allow(["127.0.0.0/8", "10.1.2.3", "fd00::/8"])
    assert address_allowed("127.9.9.9", nets) and address_allowed("10.1.2.3", nets)
    assert address_allowed("::ffff:127.0.0.1", nets) and address_allowed("fd12::1", nets)
    assert not address_allowed("10.1.2.4", nets) and not address_allowed("", nets)
    assert not address_allowed("not an address", nets)
    local = parse_allow(["localhost"])
    assert address_allowed("127.0.0.1", local) and address_allowed("::1", local)
    for bad in ("no-such-host.invalid", "10.0.0.0/40", "a b"):
        with pytest.raises(ServerSetupError, match="--allow"):
            parse_allow([bad])


@pytest.mark.parametrize("allow", ["localhost", "127.0.0.0/8"])
def test_allow_by_host_name_or_network_admits_the_peer(start_server, allow):
    srv = start_server("--lockstep", "--plant", "standin", "--allow", allow)
    client = RigClient(srv.address, timeout=2.0)
    assert client.call("hello")["ok"]
    client.close()
    assert stop_and_read_stderr(srv) == []


def test_allow_refuses_a_peer_outside_the_network_and_logs_its_address(start_server):
    srv = start_server("--lockstep", "--plant", "standin", "--allow", "10.0.0.0/8")
    client = RigClient(srv.address, timeout=0.5)
    with pytest.raises(RigConnectionError, match="did not answer"):
        client.call("hello")
    client.close()
    lines = stop_and_read_stderr(srv)
    assert any("refused" in x and "127.0.0.1" in x and "--allow" in x for x in lines), lines


def test_an_allow_entry_that_does_not_resolve_is_a_one_line_error(capsys):
    code = main(["rig", "serve-sim", "--plant", "standin", "--bind", f"tcp://127.0.0.1:{free_port()}",
                 "--allow", "no-such-host.invalid"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "--allow no-such-host.invalid" in err[0] and "resolve" in err[0]


# --- 4. CURVE keys reloaded --------------------------------------------------------------------------------
def _public_key(path) -> str:
    from magctl.rig.server import load_keypair

    return load_keypair(path)[0].decode()


def _key_file(key: str) -> str:
    """A public certificate in zmq.auth's format; every key gives a file of the same size."""
    return f'metadata\ncurve\n    public-key = "{key}"\n'


@pytest.fixture
def two_keys(tmp_path):
    lab, other = generate_keys(tmp_path / "lab"), generate_keys(tmp_path / "other")
    clients = tmp_path / "clients"
    clients.mkdir()
    (clients / "client.key").write_text(_key_file(_public_key(lab["client_public"])))
    return lab, other, clients


def _curve_client(address, lab, secret, timeout=0.5):
    return RigClient(address, timeout=timeout, curve_server_key=lab["server_public"], curve_secret=secret)


def _connects(address, lab, secret) -> bool:
    client = _curve_client(address, lab, secret)
    try:
        client.call("hello")
        return True
    except RigConnectionError:
        return False
    finally:
        client.close()


def test_removing_a_client_key_file_stops_that_client_without_a_restart(start_server, two_keys):
    """The clients' folder is polled: once its key file is gone, the client cannot connect again, and its
    open connection is refused (unauthorised). Putting the file back admits it again."""
    lab, _, clients = two_keys
    srv = start_server("--lockstep", "--plant", "standin", "--curve-secret", lab["server_secret"],
                       "--curve-clients", str(clients))
    live = _curve_client(srv.address, lab, lab["client_secret"], timeout=2.0)
    live.configure()
    live.activate()
    live.write(Command.zero())
    assert _connects(srv.address, lab, lab["client_secret"])
    (clients / "client.key").unlink()
    assert wait_until(lambda: not _connects(srv.address, lab, lab["client_secret"])), "the removed key connects"
    with pytest.raises(RigError, match="unauthorised"):
        live.call("status")
    live.session = None
    live.close()
    (clients / "client.key").write_text(_key_file(_public_key(lab["client_public"])))
    assert wait_until(lambda: _connects(srv.address, lab, lab["client_secret"])), "the key put back is refused"
    client = _curve_client(srv.address, lab, lab["client_secret"], timeout=2.0)
    st = client.call("status")
    assert st["key_reloads"] >= 2 and st["unauthorised"] >= 1 and st["coils_zero"] and not st["owned"]
    client.close()
    lines = stop_and_read_stderr(srv)
    assert any("CURVE client keys reloaded" in x and "1 removed" in x for x in lines), lines


def test_sighup_reloads_the_client_keys(start_server, two_keys):
    """A key file rewritten in place with its old size and mtime (the folder poll cannot see it): SIGHUP makes
    the server read the folder again; the server keeps running."""
    lab, other, clients = two_keys
    srv = start_server("--lockstep", "--plant", "standin", "--curve-secret", lab["server_secret"],
                       "--curve-clients", str(clients))
    address = srv.address
    assert _connects(address, lab, lab["client_secret"]) and not _connects(address, lab, other["client_secret"])
    f = clients / "client.key"
    st = f.stat()
    text = _key_file(_public_key(other["client_public"]))
    assert len(text) == st.st_size
    f.write_text(text)
    os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns))
    time.sleep(1.5)  # a poll of the folder passes: it sees no change
    assert _connects(address, lab, lab["client_secret"])
    srv.proc.send_signal(signal.SIGHUP)
    assert wait_until(lambda: _connects(address, lab, other["client_secret"])), "SIGHUP did not reload the keys"
    assert not _connects(address, lab, lab["client_secret"]) and srv.proc.poll() is None
    assert any("reloaded" in x for x in stop_and_read_stderr(srv))


# --- 5. honest counters ------------------------------------------------------------------------------------
def test_replies_a_pipelining_client_never_reads_are_counted_as_dropped(start_server):
    """A DEALER sends thousands of requests without reading: its queues fill and the server cannot deliver
    every reply. Each reply either reaches the client or is counted in dropped_replies (ROUTER_MANDATORY: a
    full queue raises instead of dropping silently)."""
    srv = start_server("--lockstep", "--plant", "standin")
    ctx = zmq.Context.instance()
    d = ctx.socket(zmq.DEALER)
    d.setsockopt(zmq.LINGER, 0)
    d.setsockopt(zmq.RCVHWM, 1)
    d.setsockopt(zmq.RCVBUF, 4096)
    d.connect(srv.address)
    n = 8000
    for i in range(n):
        d.send_multipart([b"", json.dumps(P.request("hello", i)).encode()])
    watcher = Raw(srv.address)
    # every request handled: the DEALER's n and the watcher's own status requests (this one included)
    assert wait_until(lambda: watcher.op("status")["requests"] - watcher.id >= n, timeout=60), "not all handled"
    got = 0
    while d.poll(1000):
        d.recv_multipart()
        got += 1
    st = watcher.op("status")
    assert st["dropped_replies"] > 0 and got + st["dropped_replies"] == n, (got, st["dropped_replies"])
    d.close(0)
    watcher.close()


# --- 6. lock-step: the owner's reads advance the clock ------------------------------------------------------
def test_in_lock_step_an_onlookers_reads_do_not_step_the_plant(start_server):
    srv = start_server("--lockstep", "--plant", "standin")
    owner, onlooker = Raw(srv.address), Raw(srv.address)
    assert owner.op("configure")["ok"] and owner.op("activate")["ok"] and owner.op("write", cmd=moving())["ok"]
    frame = owner.op("status")["frame"]
    for _ in range(3 * int(WATCHDOG / PERIOD) + 3):  # far more than the watchdog's frames
        r = onlooker.op("read")
        assert r["ok"] and r["obs"]["frame"] == frame
    st = owner.op("status")
    assert st["state"] == "active" and not st["coils_zero"] and st["watchdog_trips"] == 0 and st["frame"] == frame
    # the owner's reads do step it, and its own silence trips the watchdog as ever
    for _ in range(int(WATCHDOG / PERIOD) + 1):
        owner.op("read")
    st = owner.op("status")
    assert st["frame"] == frame + int(WATCHDOG / PERIOD) + 1 and st["coils_zero"] and st["watchdog_trips"] == 1
    # a free rig steps for anyone who reads it
    assert owner.op("deactivate")["ok"]
    before = onlooker.op("read")["obs"]["frame"]
    assert onlooker.op("read")["obs"]["frame"] == before + 1
    owner.close()
    onlooker.close()


# --- 7. not-owner says how to take over ---------------------------------------------------------------------
def test_not_owner_tells_cli_and_api_users_how_to_take_over(start_server, capsys):
    srv = start_server("--lockstep", "--plant", "standin")
    owner = RigClient(srv.address, timeout=2.0)
    owner.configure()
    other = RigClient(srv.address, timeout=2.0)
    with pytest.raises(RigNotOwner) as err:
        other.configure()
    assert "--takeover" in str(err.value) and "'takeover': true" in str(err.value)
    other.close()
    stranger = Raw(srv.address)
    r = stranger.op("write", session="0" * 32, cmd=moving())
    assert r["error"]["code"] == P.NOT_OWNER and "--takeover" in r["error"]["message"]
    stranger.close()
    code = main(["rig", "run", "--rig", srv.address, "--task", "goto", "--target-um", "1200", "1800",
                 "--max-ticks", "5", "--quiet"])
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "--takeover" in lines[0], lines
    owner.close()


def test_the_docs_name_the_new_options_and_codes():
    """docs/rig-protocol.md and docs/rig.md name the new options and codes."""
    proto = (ROOT / "docs" / "rig-protocol.md").read_text()
    rig = (ROOT / "docs" / "rig.md").read_text()
    for word in ("unauthorised", "takeover_interval", "ROUTER_MANDATORY", "--insecure", "SIGHUP"):
        assert word in proto, word
    for word in ("--log-max-mb", "--insecure", "--allow"):
        assert word in rig, word


def test_keys_signature_sees_added_and_removed_files(tmp_path):
    from magctl.rig.server import keys_signature, load_client_keys

    assert keys_signature(tmp_path / "missing") is None
    s0 = keys_signature(tmp_path)
    (tmp_path / "a.key").write_text(_key_file("x" * 40))
    s1 = keys_signature(tmp_path)
    assert s1 != s0 and load_client_keys(tmp_path)[0] == {b"x" * 40: True}
    (tmp_path / "b.key").write_text("garbage\n")
    keys, problems = load_client_keys(tmp_path)
    assert len(keys) == 1 and len(problems) == 1 and "b.key" in problems[0]


def test_a_removed_owner_key_ends_the_session_with_the_coils_zeroed(tmp_path):
    """In process: the reload that drops the owner's key ends its session at once, coils zeroed."""
    (tmp_path / "a.key").write_text(_key_file("a" * 40))
    (tmp_path / "b.key").write_text(_key_file("b" * 40))
    srv = _server("tcp://127.0.0.1:1", curve_secret=tmp_path / "server.key_secret", curve_clients=tmp_path)
    srv._auth = type("Auth", (), {"certs": {}})()
    srv._load_keys(first=True)
    assert srv._client_keys == {"a" * 40, "b" * 40}
    srv.owner, srv.owner_key, srv.state = "token", "a" * 40, Lifecycle.ACTIVE
    (tmp_path / "b.key").unlink()
    srv._load_keys()
    assert srv.owner == "token" and srv.state is Lifecycle.ACTIVE  # another key went: the session stays
    (tmp_path / "a.key").unlink()
    srv._load_keys()
    assert srv.owner is None and srv.state is Lifecycle.INACTIVE and "key was removed" in srv.last_error
    assert srv._auth.certs["magctl-rig"] == {} and srv.key_reloads == 2


def test_a_stderr_nobody_reads_never_blocks_the_server(monkeypatch):
    """Lines are written by a thread of their own: with stderr blocked (a full pipe), ``log`` returns at once,
    never holding the message loop or the coil guard's lock; lines beyond the queue are dropped and counted."""
    import sys
    import threading

    release = threading.Event()

    class Blocked:
        def write(self, text):
            release.wait(30)
            return len(text)

        def flush(self):
            pass

    monkeypatch.setattr(sys, "stderr", Blocked())
    srv = _server("tcp://127.0.0.1:1")
    done = threading.Event()

    def flood():
        for k in range(1000):
            srv.log(f"line {k}", always=True)
        done.set()

    threading.Thread(target=flood, daemon=True).start()
    assert done.wait(30), "log() blocked on a blocked stderr"
    assert srv.log_lines_lost > 0 and not srv.lock.locked()
    release.set()
    srv._flush_log()
