"""Network rig: the client side of protocol v2 over ZeroMQ REQ.

Every call is one request and one reply with a timeout. A server that does not
answer in time is treated as gone: the REQ socket is closed (it cannot be
reused after a lost reply), the call raises :class:`RigConnectionError` and the
rig goes to ``error`` — the server's own watchdog then zeroes the coils.

``configure`` opens a session: the server's token goes with every later request, and only
this session may activate, write and deactivate until it deactivates (which ends the session;
a later ``activate`` opens a new one) or stays silent past the server's session timeout.
With ``curve_server_key`` and ``curve_secret`` the connection is CURVE-encrypted and the
server admits only client keys it knows.
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


class RigNotOwner(RigError):
    """The server refused an operation: another session owns the rig."""


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
    takeover : bool
        Take the rig over from another live session on ``configure`` (the server logs it).
    curve_server_key : path, optional
        The server's public key file (``magctl rig keys``): connect with CURVE.
    curve_secret : path, optional
        This client's secret key file (needed with ``curve_server_key``).
    """

    def __init__(self, address: str, *, timeout: float | None = None, limits: RigLimits | None = None,
                 params=None, reset: bool = False, takeover: bool = False, curve_server_key=None,
                 curve_secret=None):
        self.reset, self.takeover = reset, takeover
        self.session: str | None = None
        self._curve = None
        if (curve_server_key is None) != (curve_secret is None):
            raise RigError("CURVE needs both the server's public key and this client's secret key")
        if curve_server_key is not None:
            from magctl.rig.server import load_keypair

            try:
                server_public, _ = load_keypair(curve_server_key)
                public, secret = load_keypair(curve_secret)
            except (OSError, ValueError) as err:
                raise RigError(f"CURVE keys: {err}") from None
            if secret is None:
                raise RigError(f"{curve_secret}: has no secret key (use the .key_secret file)")
            self._curve = (server_public, public, secret)
        params = params or load_model("rig")
        super().__init__(limits or RigLimits.from_params(params))
        self.address = address
        self.timeout = params.runtime.request_timeout if timeout is None else float(timeout)
        rt = params.runtime
        self.configure_timeout = max(self.timeout, rt.configure_timeout if "configure_timeout" in rt else 30.0)
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
        if self._curve is not None:
            sock.curve_serverkey, sock.curve_publickey, sock.curve_secretkey = self._curve
        if self.address.startswith("tcp://["):  # an IPv6 address: ZeroMQ connects to it only with IPV6 on
            sock.setsockopt(zmq.IPV6, 1)
        sock.connect(self.address)
        self._sock = sock

    def _disconnect(self) -> None:
        if self._sock is not None:
            self._sock.close(0)
            self._sock = None

    def call(self, op: str, *, timeout: float | None = None, **fields) -> dict:
        """One request/reply (within ``timeout`` s, the request timeout by default); raises :class:`RigError`
        subclasses on error replies or timeouts."""
        if self._sock is None:
            self._connect()
        wait = self.timeout if timeout is None else float(timeout)
        self._sock.setsockopt(zmq.RCVTIMEO, int(wait * 1e3))
        self._id += 1
        if self.session is not None:
            fields.setdefault("session", self.session)
        msg = P.encode(P.request(op, self._id, **fields))
        try:
            self._sock.send(msg)
            raw = self._sock.recv()
        except zmq.Again:
            self._disconnect()
            raise RigConnectionError(
                f"rig server at {self.address} did not answer {op!r} within {wait * 1e3:.0f} ms"
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
            if code == P.NOT_OWNER:
                raise RigNotOwner(f"server refused: {text}")
            raise RigError(f"server error {code}: {text}")
        return reply

    # --- lifecycle hooks ------------------------------------------------------------------------
    def _configure(self) -> None:
        self.server_info = self.call("hello")
        self._claim(reset=self.reset)

    def _claim(self, reset: bool = False) -> None:
        fields = {"reset": reset}
        if self.takeover:
            fields["takeover"] = True
        # a configure may build the server's station (devices opened, a plant's flow solved): seconds, not frames
        reply = self.call("configure", timeout=self.configure_timeout, **fields)
        self.session = reply.get("session")
        self.n_spheres = int(reply["n_spheres"])

    def _activate(self) -> None:
        if self.session is None:  # the last deactivate ended the session: open a new one
            self._claim()
        try:
            self.call("activate")
        except RigNotOwner as err:
            # our session lapsed while the controller was prepared (the coils are off then): claim the rig
            # again, unless another client owns it now
            if "no session owns the rig" not in str(err):
                raise
            self._claim()
            self.call("activate")

    def _deactivate(self) -> None:
        self._release()

    def _release(self) -> None:
        if self.session is None:
            return
        self.call("deactivate")
        self.session = None

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
        self._release()

    def _close(self) -> None:
        # end the session whatever state the rig is in (after a watchdog trip it is still ours)
        try:
            if self.session is not None and self._sock is not None:
                self._release()
        except RigError:
            pass
        finally:
            self.session = None
            self._disconnect()

    def status(self) -> dict:
        """The server's status document (state, currents, watchdog, counters)."""
        return self.call("status")
