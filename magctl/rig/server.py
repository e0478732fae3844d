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
``takeover: true`` takes a live session over: the coils are zeroed and the takeover is logged; at most
one takeover per ``session.takeover_interval`` is accepted (the rest get ``not-owner``). In lock-step, a
``read`` steps the plant only when it comes from the owner or nobody owns the rig: an onlooker cannot
advance the owner's simulated watchdog.
With CURVE (``--curve-secret``, ``--curve-clients``) only clients whose public key is in the
folder connect at all, and a session is tied to its client's key; the folder is read again on SIGHUP and
when its files change (polled every ``KEY_POLL_S``), and a removed key can neither connect nor send
another request (``unauthorised``). ZeroMQ's ZAP hook (:class:`RigAuthenticator`, a
``zmq.auth.ThreadAuthenticator``) is always on, which also keeps stray connections from disturbing
connected clients; ``allow`` (IP addresses, networks, host names) is checked there. Without CURVE the
server binds only to loopback (127.0.0.0/8, ::1, localhost) or ipc:// / inproc:// unless ``insecure``.
Every line the server writes to stderr, takeovers and refused peers included, goes through one limit of
a line a second (:meth:`RigServer.log`).

The server enforces the current limits itself whatever the client sends.
"""

from __future__ import annotations

import collections
import ipaddress
import json
import os
import queue
import secrets
import signal
import socket
import sys
import threading
import time
from pathlib import Path

import zmq
from zmq.auth.thread import ThreadAuthenticator

from magctl import __version__
from magctl.core.errors import MagctlError
from magctl.rig import protocol as P
from magctl.rig.devices.base import DeviceError
from magctl.rig.interface import CommandRejected, Lifecycle, RigLimits
from magctl.rig.station import Station, StationFactory

# ZeroMQ drops (and disconnects) anything larger than this before we see it; between
# MAX_MESSAGE_BYTES and this the server answers with a 'too-large' error.
HARD_MAX_BYTES = 16 * P.MAX_MESSAGE_BYTES
# messages read per loop turn before the plant clock gets its turn again
BURST = 64
ZAP_DOMAIN = "magctl-rig"
# how to take a live session over, for the not-owner messages (a CLI user and an API user)
TAKEOVER_HINT = ("to take the rig over, pass --takeover to magctl rig run (or send 'takeover': true with "
                 "configure; RigClient(takeover=True))")
# seconds between two looks at the CURVE clients' folder (mtimes) for added or removed keys
KEY_POLL_S = 1.0


class ServerSetupError(MagctlError, ValueError):
    """The server cannot start as asked (an endpoint, an ``allow`` entry, keys): one line, before binding."""


def endpoint_is_local(endpoint: str) -> bool:
    """Whether a ZeroMQ endpoint is reachable from this machine only: ``ipc://``, ``inproc://`` or a TCP
    address on loopback (127.0.0.0/8, ::1, ``localhost``). An interface name (``eth0``, ``lo``), ``*`` and
    any other host are not."""
    scheme, sep, rest = endpoint.partition("://")
    if not sep:
        return False
    if scheme in ("ipc", "inproc"):
        return True
    if scheme != "tcp":
        return False
    host = rest.rpartition(":")[0]
    host = host.rpartition(";")[2]  # tcp://SOURCE;HOST:PORT is a connect form; be strict anyway
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    if host.lower() == "localhost":
        return True
    try:
        ip = ipaddress.ip_address(host)
    except ValueError:
        return False
    if ip.version == 6 and ip.ipv4_mapped is not None:
        ip = ip.ipv4_mapped
    return ip.is_loopback


def parse_allow(entries) -> list:
    """``--allow`` entries → IP networks: an IP address, a network (``127.0.0.0/8``, ``fd00::/8``) or a host
    name resolved now to all its addresses (``localhost`` → 127.0.0.1 and ::1). An entry that is none of
    these is a :class:`ServerSetupError` naming it."""
    nets = []
    for entry in entries or ():
        if isinstance(entry, (ipaddress.IPv4Network, ipaddress.IPv6Network)):
            nets.append(entry)
            continue
        text = str(entry).strip()
        try:
            nets.append(ipaddress.ip_network(text, strict=False))
            continue
        except ValueError:
            pass
        if not text or "/" in text or any(c.isspace() or ord(c) < 32 for c in text):
            raise ServerSetupError(f"--allow {text!r}: not an IP address, a network (a.b.c.d/n) or a host name")
        try:
            infos = socket.getaddrinfo(text, None, proto=socket.IPPROTO_TCP)
        except (socket.gaierror, UnicodeError, OSError) as err:
            why = getattr(err, "strerror", None) or err
            raise ServerSetupError(f"--allow {text}: not an IP address or a network, and the host name does not "
                                   f"resolve ({why})") from None
        for info in infos:
            addr = info[4][0].partition("%")[0]  # drop an IPv6 scope
            nets.append(ipaddress.ip_network(addr))
        if text.lower() == "localhost":  # whatever /etc/hosts says, localhost is both loopback addresses (RFC 6761)
            nets += [ipaddress.ip_network("127.0.0.1"), ipaddress.ip_network("::1")]
    # one entry per network, in the order given
    return list(dict.fromkeys(nets))


def address_allowed(address: str, networks) -> bool:
    """Whether a peer address (as ZeroMQ reports it) lies in one of ``networks`` (an IPv4-mapped IPv6 address
    counts as its IPv4 address); an address that does not parse is not allowed."""
    try:
        ip = ipaddress.ip_address(address.partition("%")[0])
    except ValueError:
        return False
    ips = [ip] if ip.version == 4 or ip.ipv4_mapped is None else [ip, ip.ipv4_mapped]
    return any(a in net for a in ips for net in networks if net.version == a.version)


def load_client_keys(folder) -> tuple[dict[bytes, bool], list[str]]:
    """The public keys (z85) of the ``*.key`` files in ``folder``, as ``zmq.auth.load_certificates`` reads
    them, and one line per file or folder that could not be read (such a file admits nobody)."""
    import zmq.auth

    keys: dict[bytes, bool] = {}
    problems: list[str] = []
    if not Path(folder).is_dir():
        return keys, [f"{folder}: no such folder"]
    try:
        files = sorted(Path(folder).glob("*.key"))
    except OSError as err:
        return keys, [f"{folder}: {err.strerror or err}"]
    for f in files:
        try:
            public, _ = zmq.auth.load_certificate(f)
        except (OSError, ValueError) as err:
            problems.append(f"{f.name}: {err}")
            continue
        keys[public] = True
    return keys, problems


def keys_signature(folder):
    """What changes when a ``*.key`` file of ``folder`` is added, removed, replaced or rewritten (the folder's
    and the files' mtimes, sizes and inodes); None when the folder cannot be read."""
    try:
        top = os.stat(folder).st_mtime_ns
        files = []
        with os.scandir(folder) as it:
            for e in it:
                if e.name.endswith(".key"):
                    st = e.stat()
                    files.append((e.name, st.st_mtime_ns, st.st_size, st.st_ino))
    except OSError:
        return None
    return top, tuple(sorted(files))


class RigAuthenticator(ThreadAuthenticator):
    """The ZAP handler: peers outside ``networks`` (when given) are refused before any mechanism, then
    pyzmq's checks run (NULL: admitted; CURVE: the key must be in ``certs``). ZeroMQ's own ``allow`` only
    matches exact address strings; this one matches networks and host names resolved at start.

    Refusals are queued (address, reason) for the server's message loop, which logs them at its rate of
    a line a second; :meth:`take_refusals` empties the queue.
    """

    def __init__(self, context, networks=()):
        super().__init__(context)
        self.networks = list(networks)
        self._refusals: collections.deque = collections.deque(maxlen=64)
        self._refused_lock = threading.Lock()
        self._refused_total = 0
        self._peer_address = ""  # of the ZAP request being handled (the ZAP thread handles one at a time)

    def _refused(self, address: str, reason: str) -> None:
        with self._refused_lock:
            self._refused_total += 1
            self._refusals.append((address, reason))

    def take_refusals(self) -> tuple[int, list[tuple[str, str]]]:
        """(refusals since the last call, the latest few of them as (address, reason))."""
        with self._refused_lock:
            n, items = self._refused_total, list(self._refusals)
            self._refused_total = 0
            self._refusals.clear()
        return n, items

    async def handle_zap_message(self, msg):
        if len(msg) >= 6:
            address = msg[3].decode(self.encoding, "replace")
            if self.networks and not address_allowed(address, self.networks):
                self._refused(address or "a local peer", "not in --allow")
                self._send_zap_reply(msg[1], b"400", b"Address not allowed")
                return
            self._peer_address = address
        await super().handle_zap_message(msg)

    async def _authenticate_curve(self, domain, client_key):
        allowed, reason = await super()._authenticate_curve(domain, client_key)
        if not allowed:
            why = reason.decode(self.encoding, "replace") if isinstance(reason, bytes) else str(reason)
            self._refused(self._peer_address or "a local peer",
                          f"CURVE key not authorised ({why.lower() or 'refused'})")
        return allowed, reason


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
        Peers allowed to connect (ZAP): IP addresses, networks (``10.1.0.0/16``) and host names (resolved
        here, once); all when empty. An entry that is none of these raises :class:`ServerSetupError`.
    insecure : bool
        Allow binding a non-loopback TCP address without CURVE (session tokens then travel in clear; a
        warning line says so). Without it such a ``bind`` raises :class:`ServerSetupError`.
    takeover_interval : float
        At most one takeover per this many seconds (wall clock); others get ``not-owner``.
    """

    def __init__(self, station: StationFactory, bind: str, limits: RigLimits, watchdog: float, period: float,
                 describe: dict | None = None, *, name: str = "serve-sim", lockstep: bool = False,
                 session_timeout: float = 2.0, lockstep_wall_timeout: float = 2.0, curve_secret=None,
                 curve_clients=None, allow=None, log=None, insecure: bool = False, takeover_interval: float = 1.0):
        self.station_factory, self.bind, self.limits, self.watchdog = station, bind, limits, watchdog
        self.period, self.name = period, name
        self.describe = describe or {}
        self.lockstep = lockstep
        self.session_timeout = session_timeout
        self.curve_secret = None if curve_secret is None else Path(curve_secret)
        self.curve_clients = None if curve_clients is None else Path(curve_clients)
        if (self.curve_secret is None) != (self.curve_clients is None):
            raise ServerSetupError("CURVE needs both the server's secret key and the clients' public keys folder")
        self.insecure = bool(insecure)
        if self.curve_secret is None and not self.insecure and not endpoint_is_local(bind):
            raise ServerSetupError(
                f"refusing to bind {bind} without CURVE: session tokens and commands would travel in clear to "
                f"anyone on that network; bind to loopback (tcp://127.0.0.1:PORT), use CURVE (--curve-secret, "
                f"--curve-clients) or pass --insecure")
        self.allow = parse_allow(allow)
        if self.allow and not bind.startswith("tcp://"):
            raise ServerSetupError(f"--allow filters TCP peers by address; {bind} is not a tcp:// endpoint")
        if not takeover_interval >= 0:
            raise ServerSetupError(f"takeover interval must be >= 0 s, got {takeover_interval!r}")
        self.takeover_interval = float(takeover_interval)
        self._last_takeover = -float("inf")
        self._log_fn = log
        self.state = Lifecycle.UNCONFIGURED
        self.plant: Station | None = None
        self.last_error: str | None = None
        self.activation = 0
        self.requests = self.errors = self.skipped_frames = 0
        self.bad_envelopes = self.dropped_replies = self.loop_errors = 0
        self.commands_applied = 0
        self.device_faults = 0
        self.watchdog_trips = 0
        self.tripped_after: float | None = None
        self.takeovers = self.takeovers_refused = 0
        self.refused_connections = self.unauthorised = 0
        self.key_reloads = 0
        self._client_keys: set[str] | None = None  # z85 user ids admitted with CURVE (None: no CURVE)
        self._keys_sig = None
        self._keys_checked = -float("inf")
        self._reload_keys = False
        self._auth: RigAuthenticator | None = None
        self.owner: str | None = None
        self.owner_key: str | None = None
        self.owner_seen = 0.0
        self.running = False
        self._t0 = time.monotonic()
        self._next_frame = 0.0
        self._last_log = -1e9
        self._suppressed: collections.Counter = collections.Counter()
        self._log_queue: queue.Queue = queue.Queue(maxsize=256)
        self._log_thread: threading.Thread | None = None
        self.log_lines_lost = 0
        self.lock = threading.Lock()
        self.guard = CoilGuard(lockstep_wall_timeout if lockstep else watchdog, self._guard_trip, self.lock)

    # --- clock and log --------------------------------------------------------------------------
    def now(self) -> float:
        """The rig clock: simulated time (frame · period) in lock-step mode, else monotonic."""
        if self.lockstep:
            return 0.0 if self.plant is None else self.plant.frame * self.period
        return time.monotonic() - self._t0

    def log(self, message: str, *, kind: str = "fault", always: bool = False) -> None:
        """One line to stderr, at most one a second whatever peers do: the lines in between are dropped and
        counted by ``kind`` (``fault``, ``takeover``, ``refused``, ``session``, ``dropped reply``…), and the
        next line that gets out says how many of each. ``always`` is for the server's own lines (start, exit,
        the operator's key reloads), never for anything a peer can cause."""
        if self._log_fn is not None:
            self._log_fn(message)
            return
        t = time.monotonic()
        if not always and t - self._last_log < 1.0:
            self._suppressed[kind] += 1
            return
        more = ""
        if self._suppressed:
            n = sum(self._suppressed.values())
            kinds = ", ".join(f"{c} {k}" for k, c in self._suppressed.most_common())
            more = f" (+{n} more since the last line: {kinds})"
        self._suppressed.clear()
        self._last_log = t
        # a thread of its own writes the line: a stderr nobody reads (a full pipe) blocks that thread only, never
        # the message loop or the lock the coil guard takes; lines beyond the queue are dropped and counted
        if self._log_thread is None:
            self._log_thread = threading.Thread(target=self._log_writer, name="magctl-rig-log", daemon=True)
            self._log_thread.start()
        try:
            self._log_queue.put_nowait(f"magctl {self.name}: {message}{more}")
        except queue.Full:
            self.log_lines_lost += 1

    def _log_writer(self) -> None:
        while True:
            line = self._log_queue.get()
            if line is None:
                return
            try:
                print(line, file=sys.stderr, flush=True)
            except Exception:  # noqa: BLE001 - a closed stderr must not stop the server
                pass

    def _flush_log(self, timeout: float = 2.0) -> None:
        """Let the log thread write what is queued (at exit; gives up after ``timeout`` on a blocked stderr)."""
        if self._log_thread is None:
            return
        try:
            self._log_queue.put(None, timeout=timeout)
        except queue.Full:
            return
        self._log_thread.join(timeout)
        self._log_thread = None

    # --- safety ---------------------------------------------------------------------------------
    def _zero(self) -> None:
        """Coils off, watchdog disarmed (caller holds the lock). Never raises: a coil driver that cannot confirm the
        zero is a device fault (the board's own deadline then zeroes the outputs)."""
        self.guard.disarm()
        if self.plant is not None:
            try:
                self.plant.zero()
            except Exception as err:  # noqa: BLE001 - any failure to zero is reported, never raised into the guard
                self._device_fault(err, zeroed=False)

    def _device_fault(self, err: Exception, zeroed: bool = True) -> None:
        """A device failed (caller holds the lock): coils off as far as the driver answers, inactive, the fault as
        ``last_error`` (logged)."""
        self.device_faults += 1
        if zeroed:
            self.guard.disarm()
            try:
                self.plant.zero()
            except Exception:  # noqa: BLE001 - already failing: the board's deadline is the remaining line
                zeroed = False
        if self.state is Lifecycle.ACTIVE:
            self.state = Lifecycle.INACTIVE
        outcome = "coils zeroed" if zeroed else "zeroing unconfirmed (the coil board's own deadline zeroes them)"
        self.last_error = f"device fault: {err}; {outcome}"
        self.log(self.last_error, kind="fault")

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
            keys = self._client_keys
            if keys is not None and (peer or {}).get("user_id") not in keys:
                # a connection opened before its key was removed from the clients' folder
                self.unauthorised += 1
                raise P.ProtocolError(P.UNAUTHORISED, "this client's CURVE key is no longer authorised by the "
                                                      "server (removed from its clients' folder)")
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
            self.log(f"session {self.owner[:8]} ended: no request for {self.session_timeout:g} s", kind="session")
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

    def _may_step(self, doc: dict, peer: dict) -> bool:
        """Lock-step: whether this ``read`` advances the plant. The owner's reads do, and anyone's while no
        session owns the rig (a free rig can be watched moving); an onlooker's read during a session only
        returns the latest frame, so it cannot age the owner's command past the simulated watchdog."""
        return self.owner is None or (doc.get("session") == self.owner and self._key_matches(peer))

    def _need_owner(self, doc: dict, peer: dict, op: str) -> None:
        token = doc.get("session")
        if self.owner is None:
            raise P.ProtocolError(P.NOT_OWNER, f"cannot {op}: no session owns the rig; configure it first")
        if token != self.owner or not self._key_matches(peer):
            raise P.ProtocolError(P.NOT_OWNER, f"cannot {op}: the rig is owned by another session "
                                               f"(configured by {self._owner_desc}); commands from other "
                                               f"clients are refused; {TAKEOVER_HINT}")

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
                "session_timeout_s": self.session_timeout, "owned": self.owner is not None,
                "takeover_interval_s": self.takeover_interval}

    def _op_configure(self, doc, peer):
        takeover = False
        if self.owner is not None and doc.get("session") != self.owner:
            if doc.get("takeover") is not True:
                raise P.ProtocolError(P.NOT_OWNER, f"the rig is owned by another session (configured by "
                                                   f"{self._owner_desc}, last request "
                                                   f"{time.monotonic() - self.owner_seen:.1f} s ago); "
                                                   f"{TAKEOVER_HINT}")
            since = time.monotonic() - self._last_takeover
            if since < self.takeover_interval:
                # a peer looping on takeovers would zero the coils and fill the log as fast as it sends
                self.takeovers_refused += 1
                self.log(f"takeover refused: {self._peer_desc(peer)} asked {since:.2f} s after the last one "
                         f"(at most one per {self.takeover_interval:g} s)", kind="takeover")
                raise P.ProtocolError(P.NOT_OWNER, f"takeover refused: the last takeover was {since:.2f} s ago "
                                                   f"and the server accepts at most one per "
                                                   f"{self.takeover_interval:g} s; the rig stays with its "
                                                   f"session; try again later")
            takeover = True
        elif self.owner is not None and not self._key_matches(peer):
            raise P.ProtocolError(P.NOT_OWNER, "the session token belongs to another client key")
        # coils off first, whoever asks and whatever comes next
        self._zero()
        self.state = Lifecycle.INACTIVE
        if takeover:
            self.takeovers += 1
            self._last_takeover = time.monotonic()
            self.log(f"takeover: session {self.owner[:8]} (configured by {self._owner_desc}) taken over by "
                     f"{self._peer_desc(peer)}; coils zeroed", kind="takeover")
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
        if self.lockstep and self._may_step(doc, peer):
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
        except DeviceError as err:
            self._device_fault(err)
            raise P.ProtocolError(P.DEVICE_FAULT, self.last_error) from None
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
            "takeovers_refused": self.takeovers_refused, "refused_connections": self.refused_connections,
            "unauthorised": self.unauthorised, "key_reloads": self.key_reloads,
            "log_lines_lost": self.log_lines_lost, "device_faults": self.device_faults,
            "devices": p.status() if p is not None and hasattr(p, "status") else None,
            "session_owner": doc.get("session") is not None and doc.get("session") == self.owner,
        }

    # --- timing ---------------------------------------------------------------------------------
    def _lockstep_frame(self) -> None:
        """One frame of simulated time (caller holds the lock); the watchdog counts it too."""
        p = self.plant
        t = (p.frame + 1) * self.period
        if p.last_command_t is not None and t - p.last_command_t > self.watchdog:
            self._trip(t - p.last_command_t, "simulated time")
        try:
            p.step(t)
        except DeviceError as err:
            self._device_fault(err)

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
            try:
                p.step(self._next_frame)
            except DeviceError as err:
                with self.lock:
                    self._device_fault(err)
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
            # ROUTER_MANDATORY: an unroutable reply raises instead of vanishing
            sock.send_multipart([routing, b"", reply], zmq.NOBLOCK)
        except zmq.Again:
            # the peer's queue is full (SNDHWM): it sends faster than it reads (a pipelining DEALER)
            self.dropped_replies += 1
            self.log(f"reply dropped: {peer.get('address')} does not read its replies (queue full)",
                     kind="dropped reply")
        except zmq.ZMQError as err:
            if err.errno == zmq.ETERM:
                raise
            # EHOSTUNREACH: the peer disconnected before its reply
            self.dropped_replies += 1
            self.log(f"reply not sent to {peer.get('address')}: {err}", kind="dropped reply")
        return True

    def _make_socket(self, ctx):
        sock = ctx.socket(zmq.ROUTER)
        sock.setsockopt(zmq.LINGER, 0)
        sock.setsockopt(zmq.MAXMSGSIZE, HARD_MAX_BYTES)
        sock.setsockopt(zmq.HANDSHAKE_IVL, 2000)
        sock.setsockopt(zmq.SNDHWM, 100)
        sock.setsockopt(zmq.RCVHWM, 1000)
        # a reply that cannot be queued (full queue, peer gone) raises EAGAIN/EHOSTUNREACH instead of being
        # dropped silently, so that dropped_replies counts it
        sock.setsockopt(zmq.ROUTER_MANDATORY, 1)
        if self.bind.startswith("tcp://["):  # an IPv6 address (tcp://[::1]:PORT): ZeroMQ binds it only with IPV6 on
            sock.setsockopt(zmq.IPV6, 1)
        sock.setsockopt_string(zmq.ZAP_DOMAIN, ZAP_DOMAIN)
        if self.curve_secret is not None:
            public, secret = load_keypair(self.curve_secret)
            sock.curve_secretkey = secret
            sock.curve_publickey = public
            sock.curve_server = True
        return sock

    def _start_auth(self, ctx):
        auth = RigAuthenticator(ctx, self.allow)
        self._auth = auth
        if self.curve_clients is not None:
            self._load_keys(first=True)
        auth.start()
        return auth

    # --- CURVE keys and refused peers -----------------------------------------------------------
    def _load_keys(self, first: bool = False) -> None:
        """Read the clients' folder and swap the key set the ZAP handler checks (one assignment: the ZAP
        thread sees the old set or the new one). A key no longer there cannot connect or send another
        request; if it owned the session, the session ends and the coils are zeroed."""
        sig = keys_signature(self.curve_clients)
        keys, problems = load_client_keys(self.curve_clients)
        self._keys_sig = sig
        self._auth.certs[ZAP_DOMAIN] = keys
        old = self._client_keys
        self._client_keys = {k.decode("ascii", "replace") for k in keys}
        if first:
            for problem in problems:
                self.log(f"CURVE client key not loaded: {problem}", always=True)
            return
        self.key_reloads += 1
        removed = 0 if old is None else len(old - self._client_keys)
        added = len(self._client_keys - (old or set()))
        extra = f"; unreadable: {'; '.join(problems)}" if problems else ""
        self.log(f"CURVE client keys reloaded from {self.curve_clients}: {len(keys)} key(s), {added} added, "
                 f"{removed} removed{extra}", always=True)  # the operator's doing (a file, SIGHUP), never a peer's
        with self.lock:
            if self.owner is not None and self.owner_key is not None and self.owner_key not in self._client_keys:
                if self.state is Lifecycle.ACTIVE:
                    self.state = Lifecycle.INACTIVE
                self._zero()
                self.last_error = "the owner's CURVE key was removed; session ended, coils zeroed"
                self.owner = self.owner_key = None

    def _check_keys(self) -> None:
        """Reload the CURVE keys on SIGHUP, or when the folder's files changed (looked at every KEY_POLL_S)."""
        if self.curve_clients is None or self._auth is None:
            return
        t = time.monotonic()
        if not self._reload_keys and t - self._keys_checked < KEY_POLL_S:
            return
        self._keys_checked = t
        if self._reload_keys or keys_signature(self.curve_clients) != self._keys_sig:
            self._reload_keys = False
            self._load_keys()

    def _report_refusals(self) -> None:
        """Log the connections the ZAP handler refused since the last call (one line, rate-limited)."""
        if self._auth is None:
            return
        n, items = self._auth.take_refusals()
        if not n:
            return
        self.refused_connections += n
        where = sorted({f"{a} ({r})" for a, r in items})
        self.log(f"refused {n} connection(s) from {', '.join(where[:4])}"
                 + (f" and {len(where) - 4} more" if len(where) > 4 else ""), kind="refused")

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

        def reload_keys(signum, frame):
            self._reload_keys = True

        if self.curve_secret is None and not endpoint_is_local(self.bind):
            self.log(f"warning: serving {self.bind} without CURVE (--insecure): session tokens and commands "
                     f"travel in clear, and anyone who can reach the port can read a token and command the rig",
                     always=True)
        # the coil guard needs the interpreter for a few µs when its deadline comes: let the message loop
        # hand it over after 1 ms instead of Python's default 5 ms
        switch = sys.getswitchinterval()
        sys.setswitchinterval(min(switch, 1e-3))
        old = {}
        if threading.current_thread() is threading.main_thread():
            old = {s: signal.signal(s, stop) for s in (signal.SIGTERM, signal.SIGINT)}
            if hasattr(signal, "SIGHUP"):
                old[signal.SIGHUP] = signal.signal(signal.SIGHUP, reload_keys)
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
                    self._report_refusals()
                    self._check_keys()
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
            try:
                self._report_refusals()
            except Exception:  # noqa: BLE001 - exiting anyway
                pass
            if self._suppressed:
                self.log("exiting; the last lines held back by the one-line-a-second limit are counted here",
                         always=True)
            self._flush_log()
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


def start_server(argv: list[str], *, cwd=None, env: dict | None = None, timeout: float = 60.0):
    """Start a rig server process (``argv``: a ``magctl rig serve…`` command line) and wait for its
    :func:`announce` line; returns the running :class:`subprocess.Popen` (stdout and stderr piped). A process that
    exits, or says nothing within ``timeout`` s, is killed and raises :class:`RuntimeError` with its stderr."""
    import os
    import selectors
    import subprocess

    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=cwd,
                            env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})})
    sel = selectors.DefaultSelector()
    sel.register(proc.stdout, selectors.EVENT_READ)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if sel.select(timeout=0.2):
            line = proc.stdout.readline()
            try:
                if line and json.loads(line).get("ready"):
                    return proc
            except ValueError:
                pass
        if proc.poll() is not None:
            break
    if proc.poll() is None:
        proc.kill()
    proc.wait(timeout=10)
    raise RuntimeError(f"{' '.join(map(str, argv))} did not start: {proc.stderr.read().decode(errors='replace')}")


def announce(endpoint: str) -> None:
    """The line a parent process waits for: the server is bound and serving."""
    print(json.dumps({"ready": True, "endpoint": endpoint}), flush=True)
    sys.stdout.flush()
