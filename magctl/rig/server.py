"""The rig server: one station (simulated or real devices) served over ZeroMQ in protocol v2.

``magctl rig serve-sim`` serves the simulated plant (:class:`~magctl.rig.sim.SimPlant`) and ``magctl rig serve
--config lab.toml`` a station built from device adapters (:class:`~magctl.rig.station.DeviceStation`); both are
this server, with the same protocol, sessions, CURVE, limits and coil guard. A station is anything with the
:class:`~magctl.rig.station.Station` methods.

Three independent parts, so that no byte a peer sends can keep the coils on:

* **Coil guard** (:class:`CoilGuard`, its own thread). It owns the watchdog: while the rig is
  active it sleeps until the last valid command's deadline and zeroes the coils when nothing
  newer arrived. It takes one short lock that message handling also takes for a few
  microseconds; it never waits for the socket, for parsing or for the plant.
* **Message loop** (the main thread). A ROUTER socket, read only with ``NOBLOCK`` after a poll
  whose timeout is at most the time to the next frame: a half-sent frame, a peer that never
  finishes its handshake or a message without the REQ delimiter cannot block it. Every request
  gets a reply (an error reply when it is malformed, sent to the peer's routing id); every
  failure while reading, parsing, handling or replying is caught, counted, logged to stderr
  (at most one line a second) and the loop goes on. The process exits only on SIGTERM/SIGINT.
* **Plant clock**: in real time the plant steps every frame due on the monotonic clock (missed
  frames are skipped and counted, never replayed); in **lock-step** mode (``--lockstep``) it
  steps exactly one frame per ``read``, like ``SimRig(realtime=False)``, and the watchdog also
  counts simulated time (deterministic tests). The coil guard keeps its wall-clock deadline in
  both modes (in lock-step with ``watchdog.lockstep_wall_timeout``, a backstop for a vanished
  client).

**Sessions.** ``configure`` hands out a session token; the session that configured the rig owns
it until it sends ``deactivate`` or stays silent for ``session.timeout``. ``activate``,
``deactivate`` and ``write`` from anyone else get ``not-owner``. ``configure`` with
``takeover: true`` takes a live session over: the coils are zeroed and the takeover is logged.
With CURVE (``--curve-secret``, ``--curve-clients``) only clients whose public key is in the
folder connect at all, and a session is tied to its client's key. ZeroMQ's ZAP hook
(``zmq.auth.ThreadAuthenticator``) is always on, which also keeps stray connections from
disturbing connected clients.

The server enforces the current limits itself whatever the client sends.
"""

from __future__ import annotations

import json
import secrets
import signal
import sys
import threading
import time
from pathlib import Path

import zmq

from magctl import __version__
from magctl.rig import protocol as P
from magctl.rig.interface import CommandRejected, Lifecycle, RigLimits
from magctl.rig.station import Station, StationFactory

# ZeroMQ drops (and disconnects) anything larger than this before we see it; between
# MAX_MESSAGE_BYTES and this the server answers with a 'too-large' error.
HARD_MAX_BYTES = 16 * P.MAX_MESSAGE_BYTES
# messages read per loop turn before the plant clock gets its turn again
BURST = 64
ZAP_DOMAIN = "magctl-rig"


class CoilGuard:
    """The watchdog in its own thread: zero the coils after ``timeout`` s of silence while active.

    ``fed()`` is called (under :attr:`lock`) for every valid command, ``disarm()`` when the
    coils are zeroed otherwise. ``trip`` is called under the lock with the command's age when
    the deadline passes; it must only zero the coils and change state (microseconds).
    """

    def __init__(self, timeout: float, trip, lock: threading.Lock):
        self.timeout, self.trip, self.lock = timeout, trip, lock
        self.last_fed: float | None = None
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._thread = threading.Thread(target=self._run, name="magctl-coil-guard", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout=2.0)

    def fed(self) -> None:
        first = self.last_fed is None
        self.last_fed = time.monotonic()
        if first:
            self._wake.set()

    def disarm(self) -> None:
        self.last_fed = None

    def _run(self) -> None:
        idle = max(self.timeout / 4, 1e-3)
        while not self._stop.is_set():
            fed = self.last_fed
            wait = idle if fed is None else fed + self.timeout - time.monotonic() + 1e-4
            if wait > 0:
                self._wake.wait(min(wait, idle))
                self._wake.clear()
                continue
            with self.lock:
                fed = self.last_fed
                now = time.monotonic()
                if fed is not None and now - fed > self.timeout:
                    self.last_fed = None
                    self.trip(now - fed)


class RigServer:
    """The simulated rig server.

    Parameters
    ----------
    station : callable
        Builds the station (called at the first ``configure`` and on ``reset``): a
        :class:`~magctl.rig.sim.SimPlant` or a :class:`~magctl.rig.station.DeviceStation`.
    bind : str
        ZeroMQ endpoint, e.g. ``tcp://127.0.0.1:5555``.
    limits : RigLimits
        Enforced on every ``write``.
    watchdog : float
        Seconds without a valid command before the coils are zeroed.
    period : float
        Frame period, s.
    lockstep : bool
        Step one plant frame per ``read`` (simulated time) instead of on the monotonic clock.
    session_timeout : float
        A session whose owner sent nothing for this long ends.
    lockstep_wall_timeout : float
        Wall-clock watchdog of lock-step mode (the simulated-time watchdog is ``watchdog``).
    curve_secret : path, optional
        Server secret key file (``magctl rig keys``): CURVE encryption and authentication on.
    curve_clients : path, optional
        Folder of the authorised clients' public key files (required with ``curve_secret``).
    allow : list of str, optional
        Peer IP addresses allowed to connect (ZAP); all when empty.
    """

    def __init__(self, station: StationFactory, bind: str, limits: RigLimits, watchdog: float, period: float,
                 describe: dict | None = None, *, name: str = "serve-sim", lockstep: bool = False,
                 session_timeout: float = 2.0, lockstep_wall_timeout: float = 2.0, curve_secret=None,
                 curve_clients=None, allow=None, log=None):
        self.station_factory, self.bind, self.limits, self.watchdog = station, bind, limits, watchdog
        self.period, self.name = period, name
        self.describe = describe or {}
        self.lockstep = lockstep
        self.session_timeout = session_timeout
        self.curve_secret = None if curve_secret is None else Path(curve_secret)
        self.curve_clients = None if curve_clients is None else Path(curve_clients)
        if (self.curve_secret is None) != (self.curve_clients is None):
            raise ValueError("CURVE needs both the server's secret key and the clients' public keys folder")
        self.allow = list(allow or [])
        self._log_fn = log
        self.state = Lifecycle.UNCONFIGURED
        self.plant: Station | None = None
        self.last_error: str | None = None
        self.activation = 0
        self.requests = self.errors = self.skipped_frames = 0
        self.bad_envelopes = self.dropped_replies = self.loop_errors = 0
        self.commands_applied = 0
        self.watchdog_trips = 0
        self.tripped_after: float | None = None
        self.takeovers = 0
        self.owner: str | None = None
        self.owner_key: str | None = None
        self.owner_seen = 0.0
        self.running = False
        self._t0 = time.monotonic()
        self._next_frame = 0.0
        self._last_log = -1e9
        self._suppressed = 0
        self.lock = threading.Lock()
        self.guard = CoilGuard(lockstep_wall_timeout if lockstep else watchdog, self._guard_trip, self.lock)

    # --- clock and log --------------------------------------------------------------------------
    def now(self) -> float:
        """The rig clock: simulated time (frame · period) in lock-step mode, else monotonic."""
        if self.lockstep:
            return 0.0 if self.plant is None else self.plant.frame * self.period
        return time.monotonic() - self._t0

    def log(self, message: str, *, always: bool = False) -> None:
        """One line to stderr; routine faults at most one line a second (the rest are counted)."""
        if self._log_fn is not None:
            self._log_fn(message)
            return
        t = time.monotonic()
        if not always and t - self._last_log < 1.0:
            self._suppressed += 1
            return
        more = f" (+{self._suppressed} more since the last line)" if self._suppressed else ""
        self._suppressed = 0
        self._last_log = t
        try:
            print(f"magctl {self.name}: {message}{more}", file=sys.stderr, flush=True)
        except Exception:  # noqa: BLE001 - a closed stderr must not stop the server
            pass

    # --- safety ---------------------------------------------------------------------------------
    def _zero(self) -> None:
        """Coils off, watchdog disarmed (caller holds the lock)."""
        if self.plant is not None:
            self.plant.zero()
        self.guard.disarm()

    def _trip(self, age: float, clock: str) -> None:
        self._zero()
        self.watchdog_trips += 1
        self.tripped_after = age
        if self.state is Lifecycle.ACTIVE:
            self.state = Lifecycle.INACTIVE
        self.last_error = f"watchdog: no valid command for {age * 1e3:.0f} ms ({clock}); coils zeroed"

    def _guard_trip(self, age: float) -> None:
        self._trip(age, "wall clock")

    # --- request handling -----------------------------------------------------------------------
    def handle(self, raw: bytes, peer: dict | None = None) -> bytes:
        """Answer one raw request; never raises, and the reply always encodes."""
        self.requests += 1
        rid = None
        try:
            doc = P.parse_request(raw)
            rid = doc["id"]
            with self.lock:
                self._session_seen(doc, peer or {})
                reply = getattr(self, "_op_" + doc["op"])(doc, peer or {})
            return P.encode(P.ok_reply(rid, **reply))
        except P.ProtocolError as err:
            self.errors += 1
            return P.encode_error(err.request_id if rid is None else rid, err.code, str(err))
        except Exception as err:  # noqa: BLE001 - the server keeps serving whatever happens
            self.errors += 1
            self.log(f"internal error on a request: {type(err).__name__}: {err}")
            return P.encode_error(rid, P.INTERNAL, f"{type(err).__name__}: {P.show(str(err), 200)}")

    def _need(self, *states: Lifecycle, op: str) -> None:
        if self.state not in states:
            why = f" ({self.last_error})" if self.last_error else ""
            raise P.ProtocolError(P.BAD_STATE, f"cannot {op}: rig is {self.state.value}{why}")

    def _expire_session(self) -> None:
        if self.owner is not None and time.monotonic() - self.owner_seen > self.session_timeout:
            self.log(f"session {self.owner[:8]} ended: no request for {self.session_timeout:g} s", always=True)
            if self.state is Lifecycle.ACTIVE:
                self._zero()
                self.state = Lifecycle.INACTIVE
                self.last_error = "session timed out; coils zeroed"
            self.owner = self.owner_key = None

    def _session_seen(self, doc: dict, peer: dict) -> None:
        self._expire_session()
        if self.owner is not None and doc.get("session") == self.owner and self._key_matches(peer):
            self.owner_seen = time.monotonic()

    def _key_matches(self, peer: dict) -> bool:
        return self.owner_key is None or peer.get("user_id") == self.owner_key

    def _need_owner(self, doc: dict, peer: dict, op: str) -> None:
        token = doc.get("session")
        if self.owner is None:
            raise P.ProtocolError(P.NOT_OWNER, f"cannot {op}: no session owns the rig; configure it first")
        if token != self.owner or not self._key_matches(peer):
            raise P.ProtocolError(P.NOT_OWNER, f"cannot {op}: the rig is owned by another session "
                                               f"(configured by {self._owner_desc}); commands from other "
                                               f"clients are refused")

    def _op_hello(self, doc, peer):
        lim = self.limits
        return {"server": f"magctl {self.name} {__version__}", "state": self.state.value,
                "frame_period_s": self.period, "watchdog_s": self.watchdog,
                "n_spheres": None if self.plant is None else self.plant.n_spheres,
                "limits": {"b_static_max_T": lim.b_static_max, "b_osc_max_T": lim.b_osc_max,
                           "freq_max_Hz": lim.freq_max, "current_max_A": lim.coils.current_max,
                           "coil_names": lim.coils.names, "coil_current_limit_A": lim.coils.current_limit.tolist()},
                "scene": self.describe, "lockstep": self.lockstep,
                "security": "curve" if self.curve_secret else "null",
                "session_timeout_s": self.session_timeout, "owned": self.owner is not None}

    def _op_configure(self, doc, peer):
        takeover = False
        if self.owner is not None and doc.get("session") != self.owner:
            if doc.get("takeover") is not True:
                raise P.ProtocolError(P.NOT_OWNER, f"the rig is owned by another session (configured by "
                                                   f"{self._owner_desc}, last request "
                                                   f"{time.monotonic() - self.owner_seen:.1f} s ago); send "
                                                   f"'takeover': true to take it over")
            takeover = True
        elif self.owner is not None and not self._key_matches(peer):
            raise P.ProtocolError(P.NOT_OWNER, "the session token belongs to another client key")
        # coils off first, whoever asks and whatever comes next
        self._zero()
        self.state = Lifecycle.INACTIVE
        if takeover:
            self.takeovers += 1
            self.log(f"takeover: session {self.owner[:8]} (configured by {self._owner_desc}) taken over by "
                     f"{self._peer_desc(peer)}; coils zeroed", always=True)
            self.owner = None
        if self.owner is None:
            self.owner = secrets.token_hex(16)
            self.owner_key = peer.get("user_id") if self.curve_secret else None
            self._owner_desc = self._peer_desc(peer)
        self.owner_seen = time.monotonic()
        if self.plant is None or doc.get("reset") is True:
            # building a plant can take a while: the coils are already zero, the guard disarmed
            old, self.plant = self.plant, None
            self.lock.release()
            try:
                if old is not None:
                    old.close()
                plant = self.station_factory()
            finally:
                self.lock.acquire()
            self.plant = plant
            self._next_frame = self.now() + self.period
        self._zero()
        return {"state": self.state.value, "n_spheres": self.plant.n_spheres, "session": self.owner,
                "took_over": takeover}

    @staticmethod
    def _peer_desc(peer: dict) -> str:
        addr = peer.get("address") or "an unknown address"
        key = peer.get("user_id")
        return f"{addr} (key {key[:8]}…)" if key and key != "anonymous" else str(addr)

    _owner_desc = "nobody"

    def _op_activate(self, doc, peer):
        self._need_owner(doc, peer, "activate")
        self._need(Lifecycle.INACTIVE, op="activate")
        self._zero()
        self.state = Lifecycle.ACTIVE
        self.activation += 1
        self.last_error = None
        return {"state": self.state.value, "activation": self.activation}

    def _op_deactivate(self, doc, peer):
        self._need_owner(doc, peer, "deactivate")
        self._need(Lifecycle.ACTIVE, Lifecycle.INACTIVE, op="deactivate")
        self._zero()
        self.state = Lifecycle.INACTIVE
        # deactivating ends the session: the rig is free for the next client
        self.owner = self.owner_key = None
        return {"state": self.state.value, "released": True}

    def _op_read(self, doc, peer):
        self._need(Lifecycle.INACTIVE, Lifecycle.ACTIVE, op="read")
        if self.lockstep:
            self._lockstep_frame()
        return {"state": self.state.value, "obs": P.observation_to_wire(self.plant.latest)}

    def _op_write(self, doc, peer):
        self._need_owner(doc, peer, "write")
        cmd = P.command_from_wire(doc.get("cmd"))
        self._need(Lifecycle.ACTIVE, op="write")
        try:
            currents = self.plant.apply(cmd, self.now())
        except CommandRejected as err:
            raise P.ProtocolError(P.BAD_COMMAND, str(err)) from None
        self.guard.fed()
        self.commands_applied += 1
        return {"state": self.state.value, "currents_A": currents.tolist()}

    def _op_status(self, doc, peer):
        p = self.plant
        age = None if p is None or p.last_command_t is None else self.now() - p.last_command_t
        return {
            "state": self.state.value, "last_error": self.last_error, "activation": self.activation,
            "frame": None if p is None else p.frame,
            "currents_A": None if p is None else p.latest.currents.tolist(),
            "coils_zero": True if p is None else bool(p.cmd.is_zero()),
            "command_age_s": age,
            "watchdog_trips": self.watchdog_trips,
            "watchdog_tripped_after_s": self.tripped_after,
            "requests": self.requests, "errors": self.errors, "skipped_frames": self.skipped_frames,
            "bad_envelopes": self.bad_envelopes, "dropped_replies": self.dropped_replies,
            "loop_errors": self.loop_errors, "commands_applied": self.commands_applied,
            "owned": self.owner is not None, "takeovers": self.takeovers, "lockstep": self.lockstep,
            "session_owner": doc.get("session") is not None and doc.get("session") == self.owner,
        }

    # --- timing ---------------------------------------------------------------------------------
    def _lockstep_frame(self) -> None:
        """One frame of simulated time (caller holds the lock); the watchdog counts it too."""
        p = self.plant
        t = (p.frame + 1) * self.period
        if p.last_command_t is not None and t - p.last_command_t > self.watchdog:
            self._trip(t - p.last_command_t, "simulated time")
        p.step(t)

    def _tick(self) -> None:
        """Real-time plant clock: step every frame due (missed ones skipped and counted)."""
        p = self.plant
        if p is None or self.lockstep:
            return
        now = self.now()
        behind = int((now - self._next_frame) // self.period)
        if behind >= 1:
            self.skipped_frames += behind
            self._next_frame += behind * self.period
        if now >= self._next_frame:
            # the step reads the held command once; the guard may zero it at any time meanwhile
            p.step(self._next_frame)
            self._next_frame += self.period

    def _timeout_ms(self) -> int:
        if self.plant is None or self.lockstep:
            return 50
        return max(0, min(50, int((self._next_frame - self.now()) * 1e3 + 0.999)))

    def _peer(self, frame) -> dict:
        peer = {}
        for key, prop in (("address", "Peer-Address"), ("user_id", "User-Id")):
            try:
                peer[key] = frame.get(prop)
            except (zmq.ZMQError, AttributeError, UnicodeDecodeError):
                peer[key] = None
        return peer

    def _serve_one(self, sock) -> bool:
        """Read one message without blocking and answer it; False when none was waiting."""
        try:
            frames = sock.recv_multipart(zmq.NOBLOCK, copy=False)
        except zmq.Again:
            return False
        routing = frames[0].bytes
        rest = frames[1:]
        peer = self._peer(frames[-1])
        if len(rest) == 2 and len(rest[0]) == 0:
            reply = self.handle(rest[1].bytes, peer)
        else:
            # not a REQ envelope (e.g. a DEALER without the empty delimiter, or several body frames)
            self.requests += 1
            self.errors += 1
            self.bad_envelopes += 1
            self.log(f"bad envelope from {peer.get('address')}: {len(rest)} frame(s) after the routing id")
            reply = P.encode_error(None, P.BAD_ENVELOPE, f"a request is one frame after an empty delimiter "
                                                         f"(REQ socket); got {len(rest)} frame(s)")
        try:
            sock.send_multipart([routing, b"", reply], zmq.NOBLOCK)
        except zmq.Again:
            self.dropped_replies += 1
        except zmq.ZMQError as err:
            if err.errno == zmq.ETERM:
                raise
            self.dropped_replies += 1
            self.log(f"reply not sent: {err}")
        return True

    def _make_socket(self, ctx):
        sock = ctx.socket(zmq.ROUTER)
        sock.setsockopt(zmq.LINGER, 0)
        sock.setsockopt(zmq.MAXMSGSIZE, HARD_MAX_BYTES)
        sock.setsockopt(zmq.HANDSHAKE_IVL, 2000)
        sock.setsockopt(zmq.SNDHWM, 100)
        sock.setsockopt(zmq.RCVHWM, 1000)
        sock.setsockopt_string(zmq.ZAP_DOMAIN, ZAP_DOMAIN)
        if self.curve_secret is not None:
            public, secret = load_keypair(self.curve_secret)
            sock.curve_secretkey = secret
            sock.curve_publickey = public
            sock.curve_server = True
        return sock

    def _start_auth(self, ctx):
        from zmq.auth.thread import ThreadAuthenticator

        auth = ThreadAuthenticator(ctx)
        auth.start()
        if self.allow:
            auth.allow(*self.allow)
        if self.curve_clients is not None:
            auth.configure_curve(domain=ZAP_DOMAIN, location=str(self.curve_clients))
        return auth

    def serve(self, ready=None) -> int:
        """Serve until SIGTERM/SIGINT; returns the exit status. Only binding can raise."""
        ctx = zmq.Context()
        auth = sock = None
        try:
            auth = self._start_auth(ctx)
            sock = self._make_socket(ctx)
            sock.bind(self.bind)
        except BaseException:
            if sock is not None:
                sock.close(0)
            if auth is not None:
                auth.stop()
            ctx.term()
            raise
        self.running = True

        def stop(signum, frame):
            self.running = False

        # the coil guard needs the interpreter for a few µs when its deadline comes: let the message loop
        # hand it over after 1 ms instead of Python's default 5 ms
        switch = sys.getswitchinterval()
        sys.setswitchinterval(min(switch, 1e-3))
        old = {}
        if threading.current_thread() is threading.main_thread():
            old = {s: signal.signal(s, stop) for s in (signal.SIGTERM, signal.SIGINT)}
        self.guard.start()
        if ready is not None:
            ready(sock.getsockopt_string(zmq.LAST_ENDPOINT))
        poller = zmq.Poller()
        poller.register(sock, zmq.POLLIN)
        try:
            while self.running:
                try:
                    if poller.poll(self._timeout_ms()):
                        for _ in range(BURST):
                            if not self._serve_one(sock):
                                break
                            if not self.lockstep and self.now() >= self._next_frame:
                                break
                    self._tick()
                except zmq.ContextTerminated:
                    break
                except Exception as err:  # noqa: BLE001 - the loop ends only when told to
                    self.loop_errors += 1
                    self.log(f"serve loop: {type(err).__name__}: {err}")
        finally:
            with self.lock:
                self._zero()
                if self.state is Lifecycle.ACTIVE:
                    self.state = Lifecycle.INACTIVE
                if self.plant is not None:
                    self.plant.close()
            self.guard.stop()
            sys.setswitchinterval(switch)
            for s, h in old.items():
                signal.signal(s, h)
            sock.close(0)
            auth.stop()
            ctx.term()
        return 0


# --- keys -----------------------------------------------------------------------------------------------
def load_keypair(path) -> tuple[bytes, bytes]:
    """(public, secret) of a ``zmq.auth`` certificate file; a public-only file gives secret None."""
    import zmq.auth

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such key file")
    try:
        public, secret = zmq.auth.load_certificate(path)
    except (ValueError, OSError) as err:
        raise ValueError(f"{path}: not a ZeroMQ certificate file ({err})") from None
    return public, secret


def generate_keys(folder) -> dict[str, str]:
    """Server and client key pairs in ``folder`` (``zmq.auth.create_certificates``), clients' public
    keys in ``folder/clients``; returns the paths."""
    import os

    import zmq.auth

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    clients = folder / "clients"
    clients.mkdir(exist_ok=True)
    for name in ("server", "client"):
        if (folder / f"{name}.key_secret").exists():
            raise FileExistsError(f"{folder / (name + '.key_secret')} exists; keys are never overwritten")
    server_pub, server_sec = zmq.auth.create_certificates(folder, "server")
    client_pub, client_sec = zmq.auth.create_certificates(folder, "client")
    for p in (server_sec, client_sec):
        os.chmod(p, 0o600)
    (clients / "client.key").write_bytes(Path(client_pub).read_bytes())
    return {"server_secret": str(server_sec), "server_public": str(server_pub), "client_secret": str(client_sec),
            "client_public": str(client_pub), "clients_folder": str(clients)}


def announce(endpoint: str) -> None:
    """The line a parent process waits for: the server is bound and serving."""
    print(json.dumps({"ready": True, "endpoint": endpoint}), flush=True)
    sys.stdout.flush()
