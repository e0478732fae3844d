"""``magctl rig serve-sim``: the simulated rig as a server speaking protocol v1 over ZeroMQ REP.

One thread does everything, in this order, forever:

1. wait for a request until the next frame or the watchdog deadline, whichever is first;
2. answer it (a bad request gets an error reply and changes nothing);
3. zero the coils if the last valid command is older than the watchdog timeout
   (the rig then becomes inactive: the client must reactivate explicitly);
4. step the plant for every frame that is due on the monotonic clock. If the
   loop fell behind by more than a frame, the missed frames are skipped and
   counted, never replayed.

The server enforces the current limits itself whatever the client sends.
"""

from __future__ import annotations

import json
import signal
import sys
import time

import zmq

from magctl import __version__
from magctl.rig import protocol as P
from magctl.rig.interface import CommandRejected, Lifecycle, RigLimits
from magctl.rig.sim import PlantFactory, SimPlant

# ZeroMQ drops (and disconnects) anything larger than this before we see it; between
# MAX_MESSAGE_BYTES and this the server answers with a 'too-large' error.
HARD_MAX_BYTES = 16 * P.MAX_MESSAGE_BYTES


class RigServer:
    """The simulated rig server.

    Parameters
    ----------
    factory : callable
        Plant factory (see :func:`magctl.rig.plant.build_sim_plant`).
    bind : str
        ZeroMQ endpoint, e.g. ``tcp://127.0.0.1:5555``.
    limits : RigLimits
        Enforced on every ``write``.
    watchdog : float
        Seconds without a valid command before the coils are zeroed.
    period : float
        Frame period, s.
    """

    def __init__(self, factory: PlantFactory, bind: str, limits: RigLimits, watchdog: float, period: float,
                 seed: int = 0, describe: dict | None = None):
        self.factory, self.bind, self.limits, self.watchdog, self.period = factory, bind, limits, watchdog, period
        self.seed = seed
        self.describe = describe or {}
        self.state = Lifecycle.UNCONFIGURED
        self.plant: SimPlant | None = None
        self.last_error: str | None = None
        self.activation = 0
        self.requests = 0
        self.errors = 0
        self.skipped_frames = 0
        self.running = False
        self._t0 = time.monotonic()

    # --- clock ----------------------------------------------------------------------------------
    def now(self) -> float:
        return time.monotonic() - self._t0

    # --- request handling -----------------------------------------------------------------------
    def handle(self, raw: bytes) -> bytes:
        """Answer one raw request; never raises."""
        self.requests += 1
        rid = None
        try:
            doc = P.parse_request(raw)
            rid = doc["id"]
            reply = getattr(self, "_op_" + doc["op"])(doc)
            return P.encode(P.ok_reply(rid, **reply))
        except P.ProtocolError as err:
            self.errors += 1
            return P.encode(P.error_reply(err.request_id if rid is None else rid, err.code, str(err)))
        except Exception as err:  # noqa: BLE001 - the server keeps serving whatever happens
            self.errors += 1
            return P.encode(P.error_reply(rid, P.INTERNAL, f"{type(err).__name__}: {err}"))

    def _need(self, *states: Lifecycle, op: str) -> None:
        if self.state not in states:
            why = f" ({self.last_error})" if self.last_error else ""
            raise P.ProtocolError(P.BAD_STATE, f"cannot {op}: rig is {self.state.value}{why}")

    def _op_hello(self, doc):
        lim = self.limits
        return {"server": f"magctl serve-sim {__version__}", "state": self.state.value,
                "frame_period_s": self.period, "watchdog_s": self.watchdog,
                "n_spheres": None if self.plant is None else self.plant.n_spheres,
                "limits": {"b_static_max_T": lim.b_static_max, "b_osc_max_T": lim.b_osc_max,
                           "freq_max_Hz": lim.freq_max, "current_max_A": lim.coils.current_max,
                           "coil_names": lim.coils.names, "coil_current_limit_A": lim.coils.current_limit.tolist()},
                "scene": self.describe}

    def _op_configure(self, doc):
        # from any state: a new client takes over a rig left active by one that went away
        if self.plant is None or doc.get("reset") is True:
            self.plant = SimPlant(self.factory, self.limits, self.watchdog, self.seed, self.period)
            self._next_frame = self.now() + self.period
        self.plant.zero()
        self.state = Lifecycle.INACTIVE
        return {"state": self.state.value, "n_spheres": self.plant.n_spheres}

    def _op_activate(self, doc):
        self._need(Lifecycle.INACTIVE, op="activate")
        self.plant.zero()
        self.state = Lifecycle.ACTIVE
        self.activation += 1
        self.last_error = None
        return {"state": self.state.value, "activation": self.activation}

    def _op_deactivate(self, doc):
        self._need(Lifecycle.ACTIVE, Lifecycle.INACTIVE, op="deactivate")
        self.plant.zero()
        self.state = Lifecycle.INACTIVE
        return {"state": self.state.value}

    def _op_read(self, doc):
        self._need(Lifecycle.INACTIVE, Lifecycle.ACTIVE, op="read")
        return {"state": self.state.value, "obs": P.observation_to_wire(self.plant.latest)}

    def _op_write(self, doc):
        cmd = P.command_from_wire(doc.get("cmd"))
        self._need(Lifecycle.ACTIVE, op="write")
        try:
            currents = self.plant.apply(cmd, self.now())
        except CommandRejected as err:
            raise P.ProtocolError(P.BAD_COMMAND, str(err)) from None
        return {"state": self.state.value, "currents_A": currents.tolist()}

    def _op_status(self, doc):
        p = self.plant
        age = None if p is None or p.last_command_t is None else self.now() - p.last_command_t
        return {
            "state": self.state.value, "last_error": self.last_error, "activation": self.activation,
            "frame": None if p is None else p.frame,
            "currents_A": None if p is None else p.latest.currents.tolist(),
            "coils_zero": True if p is None else bool(p.cmd.is_zero()),
            "command_age_s": age,
            "watchdog_trips": 0 if p is None else p.watchdog_trips,
            "watchdog_tripped_after_s": None if p is None else p.tripped_at,
            "requests": self.requests, "errors": self.errors, "skipped_frames": self.skipped_frames,
        }

    # --- timing ---------------------------------------------------------------------------------
    def _tick(self) -> None:
        p = self.plant
        if p is None:
            return
        now = self.now()
        if p.check_watchdog(now) and self.state is Lifecycle.ACTIVE:
            self.state = Lifecycle.INACTIVE
            self.last_error = f"watchdog: no valid command for {p.tripped_at * 1e3:.0f} ms; coils zeroed"
        behind = int((now - self._next_frame) // self.period)
        if behind >= 1:
            self.skipped_frames += behind
            self._next_frame += behind * self.period
        if now >= self._next_frame:
            p.step(self._next_frame)
            self._next_frame += self.period

    def _timeout_ms(self) -> int:
        if self.plant is None:
            return 100
        due = self._next_frame
        dl = self.plant.watchdog_deadline()
        if dl is not None and self.state is Lifecycle.ACTIVE:
            due = min(due, dl + 1e-4)
        return max(0, int((due - self.now()) * 1e3 + 0.999))

    def serve(self, ready=None) -> int:
        """Serve until SIGTERM/SIGINT; returns the exit status."""
        ctx = zmq.Context()
        sock = ctx.socket(zmq.REP)
        sock.setsockopt(zmq.LINGER, 0)
        sock.setsockopt(zmq.MAXMSGSIZE, HARD_MAX_BYTES)
        sock.bind(self.bind)
        self.running = True

        def stop(signum, frame):
            self.running = False

        old = {s: signal.signal(s, stop) for s in (signal.SIGTERM, signal.SIGINT)}
        if ready is not None:
            ready(sock.getsockopt_string(zmq.LAST_ENDPOINT))
        poller = zmq.Poller()
        poller.register(sock, zmq.POLLIN)
        try:
            while self.running:
                if poller.poll(self._timeout_ms()):
                    raw = sock.recv(copy=True)
                    sock.send(self.handle(raw))
                self._tick()
        finally:
            if self.plant is not None:
                self.plant.zero()
            for s, h in old.items():
                signal.signal(s, h)
            sock.close(0)
            ctx.term()
        return 0


def announce(endpoint: str) -> None:
    """The line a parent process waits for: the server is bound and serving."""
    print(json.dumps({"ready": True, "endpoint": endpoint}), flush=True)
    sys.stdout.flush()
