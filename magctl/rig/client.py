"""Network rig: the client side of protocol v1 over ZeroMQ REQ.

Every call is one request and one reply with a timeout. A server that does not
answer in time is treated as gone: the REQ socket is closed (it cannot be
reused after a lost reply), the call raises :class:`RigConnectionError` and the
rig goes to ``error`` — the server's own watchdog then zeroes the coils.
"""

from __future__ import annotations

import zmq

from magctl.config import load_model
from magctl.rig import protocol as P
from magctl.rig.interface import (
    Command,
    CommandRejected,
    Lifecycle,
    Observation,
    Rig,
    RigConnectionError,
    RigError,
    RigLimits,
    RigStateError,
)


class RigClient(Rig):
    """A rig reached over the network.

    Parameters
    ----------
    address : str
        ZeroMQ endpoint of the server, e.g. ``tcp://127.0.0.1:5555``.
    timeout : float
        Seconds to wait for each reply.
    limits : RigLimits
        Client-side limits (the server enforces its own as well).
    reset : bool
        Ask a simulated rig to restart its scene on ``configure`` (real rigs ignore it).
    """

    def __init__(self, address: str, *, timeout: float | None = None, limits: RigLimits | None = None,
                 params=None, reset: bool = False):
        self.reset = reset
        params = params or load_model("rig")
        super().__init__(limits or RigLimits.from_params(params))
        self.address = address
        self.timeout = params.runtime.request_timeout if timeout is None else float(timeout)
        self._ctx = zmq.Context.instance()
        self._sock = None
        self._id = 0
        self.server_info: dict = {}

    # --- transport ------------------------------------------------------------------------------
    def _connect(self) -> None:
        sock = self._ctx.socket(zmq.REQ)
        sock.setsockopt(zmq.LINGER, 0)
        ms = int(self.timeout * 1e3)
        sock.setsockopt(zmq.RCVTIMEO, ms)
        sock.setsockopt(zmq.SNDTIMEO, ms)
        sock.connect(self.address)
        self._sock = sock

    def _disconnect(self) -> None:
        if self._sock is not None:
            self._sock.close(0)
            self._sock = None

    def call(self, op: str, **fields) -> dict:
        """One request/reply; raises :class:`RigError` subclasses on error replies or timeouts."""
        if self._sock is None:
            self._connect()
        self._id += 1
        msg = P.encode(P.request(op, self._id, **fields))
        try:
            self._sock.send(msg)
            raw = self._sock.recv()
        except zmq.Again:
            self._disconnect()
            raise RigConnectionError(
                f"rig server at {self.address} did not answer {op!r} within {self.timeout * 1e3:.0f} ms"
            ) from None
        except zmq.ZMQError as err:
            self._disconnect()
            raise RigConnectionError(f"rig server at {self.address}: {err}") from None
        try:
            reply = P.decode(raw)
        except P.ProtocolError as err:
            raise RigError(f"bad reply from {self.address}: {err}") from None
        if reply.get("protocol") != P.PROTOCOL or reply.get("version") != P.VERSION:
            raise RigError(f"rig server at {self.address} speaks {reply.get('protocol')!r} version "
                           f"{reply.get('version')!r}; this client speaks {P.PROTOCOL!r} version {P.VERSION}")
        if reply.get("id") != self._id:
            raise RigError(f"reply id {reply.get('id')!r} does not match request id {self._id}")
        if not reply.get("ok"):
            e = reply.get("error") or {}
            code, text = e.get("code", "?"), e.get("message", "")
            if code == P.BAD_COMMAND:
                raise CommandRejected(f"server rejected the command: {text}")
            if code == P.BAD_STATE:
                raise RigStateError(f"server: {text}")
            raise RigError(f"server error {code}: {text}")
        return reply

    # --- lifecycle hooks ------------------------------------------------------------------------
    def _configure(self) -> None:
        self.server_info = self.call("hello")
        reply = self.call("configure", reset=self.reset)
        self.n_spheres = int(reply["n_spheres"])

    def _activate(self) -> None:
        self.call("activate")

    def _deactivate(self) -> None:
        self.call("deactivate")

    def _read(self) -> Observation:
        reply = self.call("read")
        obs = P.observation_from_wire(reply["obs"])
        if reply.get("state") != Lifecycle.ACTIVE.value and self.state is Lifecycle.ACTIVE:
            # the server left 'active' on its own (watchdog): mirror it, coils are already zero
            self.state = Lifecycle.INACTIVE
            self.last_error = f"server is {reply.get('state')}: {self.status().get('last_error')}"
        return obs

    def _write(self, cmd: Command) -> None:
        self.call("write", cmd=P.command_to_wire(cmd))

    def _zero(self) -> None:
        # 'deactivate' zeroes the coils and is accepted whether or not the server is still active
        self.call("deactivate")

    def _close(self) -> None:
        self._disconnect()

    def status(self) -> dict:
        """The server's status document (state, currents, watchdog, counters)."""
        return self.call("status")
