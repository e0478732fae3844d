"""Wire format of the rig protocol, version 2 (docs/rig-protocol.md).

Every message is one UTF-8 JSON object of at most :data:`MAX_MESSAGE_BYTES`
bytes. Requests carry ``protocol``, ``version``, ``id`` and ``op``; replies echo
``id`` and carry ``ok`` plus either the result fields or ``error`` with a
``code`` and a ``message``. Quantities are SI with the unit in the key
(``b_static_T``, ``robot_est_m``, ``t_s``). NaN and infinities are not JSON and
are rejected.

This module is pure: encoding, decoding and validation, no sockets.
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np

from magctl.rig.interface import Command, CommandRejected, Observation

PROTOCOL = "magctl-rig"
VERSION = 2  # 2: sessions (a required 'session' token on activate/deactivate/write)
MAX_MESSAGE_BYTES = 65536
OPS = ("hello", "configure", "activate", "deactivate", "read", "write", "status")
# operations that change the rig: only the session that configured it (its owner) may send them
OWNER_OPS = ("activate", "deactivate", "write")
# request ids are JSON integers a 64-bit signed integer can hold
ID_MIN, ID_MAX = -(2**63), 2**63 - 1

# error codes
BAD_JSON = "bad-json"
TOO_LARGE = "too-large"
BAD_VERSION = "bad-version"
BAD_REQUEST = "bad-request"
BAD_COMMAND = "bad-command"
BAD_STATE = "bad-state"
NOT_OWNER = "not-owner"
BAD_ENVELOPE = "bad-envelope"
INTERNAL = "internal"
# with CURVE: a request on a connection whose client key was removed from the server's folder since it connected
UNAUTHORISED = "unauthorised"
DEVICE_FAULT = "device-fault"


class ProtocolError(Exception):
    """A message that must be answered with an error reply; ``code`` is one of the codes above."""

    def __init__(self, code: str, message: str, request_id=None):
        super().__init__(message)
        self.code, self.request_id = code, request_id


def _reject_constant(name: str):
    raise ProtocolError(BAD_JSON, f"{name} is not allowed (JSON numbers must be finite)")


def _reject_float(text: str) -> float:
    x = float(text)
    if x != x or x in (float("inf"), float("-inf")):
        raise ProtocolError(BAD_JSON, f"number {text[:40]!r} is not finite as a float64")
    return x


def _int(text: str) -> int:
    if len(text.lstrip("-")) > 40:
        raise ProtocolError(BAD_JSON, f"integer of {len(text)} digits is too large")
    return int(text)


def encode(doc: dict[str, Any]) -> bytes:
    """Serialise a message; raises ``ValueError`` on NaN/inf."""
    return json.dumps(doc, allow_nan=False, separators=(",", ":")).encode()


def decode(raw: bytes) -> dict[str, Any]:
    """Parse a message: size, UTF-8, JSON object, finite numbers (raises :class:`ProtocolError`)."""
    if len(raw) > MAX_MESSAGE_BYTES:
        raise ProtocolError(TOO_LARGE, f"message of {len(raw)} bytes exceeds {MAX_MESSAGE_BYTES} bytes")
    try:
        doc = json.loads(raw.decode("utf-8"), parse_constant=_reject_constant, parse_float=_reject_float,
                         parse_int=_int)
    except ProtocolError:
        raise
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ProtocolError(BAD_JSON, f"not a UTF-8 JSON document: {err}") from None
    except (RecursionError, ValueError, OverflowError) as err:
        raise ProtocolError(BAD_JSON, f"not a valid JSON document: {type(err).__name__}") from None
    if not isinstance(doc, dict):
        raise ProtocolError(BAD_JSON, f"message must be a JSON object, got {type(doc).__name__}")
    return doc


def request(op: str, request_id: int, **fields) -> dict[str, Any]:
    return {"protocol": PROTOCOL, "version": VERSION, "id": request_id, "op": op, **fields}


def valid_id(rid) -> bool:
    """A request id: a JSON integer (not a boolean, not a float) within 64 bits."""
    return type(rid) is int and ID_MIN <= rid <= ID_MAX


def echo_id(rid):
    """The id to echo in a reply: the request's if it is a valid id, else null (always encodable)."""
    return rid if valid_id(rid) else None


def show(value, limit: int = 60) -> str:
    """A short, printable rendering of a received value for error messages."""
    try:
        text = repr(value)
    except Exception:  # noqa: BLE001 - e.g. an int too long to print
        text = f"<{type(value).__name__}>"
    return text if len(text) <= limit else text[: limit - 1] + "…"


def parse_request(raw: bytes) -> dict[str, Any]:
    """Decode and check a request's envelope: protocol, version, id, known op, typed optional fields."""
    doc = decode(raw)
    rid = echo_id(doc.get("id"))
    if doc.get("protocol") != PROTOCOL:
        raise ProtocolError(BAD_REQUEST, f"'protocol' must be {PROTOCOL!r}, got {show(doc.get('protocol'))}", rid)
    version = doc.get("version")
    if type(version) is not int or version != VERSION:
        raise ProtocolError(BAD_VERSION, f"protocol version {show(version)} not supported (server speaks "
                                         f"version {VERSION}, an integer)", rid)
    if not valid_id(doc.get("id")):
        raise ProtocolError(BAD_REQUEST, f"'id' must be an integer within 64 bits, got {show(doc.get('id'))}", None)
    op = doc.get("op")
    if not isinstance(op, str) or op not in OPS:
        raise ProtocolError(BAD_REQUEST, f"unknown op {show(op)}; ops: {', '.join(OPS)}", rid)
    for key, kind in (("reset", bool), ("takeover", bool), ("session", str)):
        if key in doc and type(doc[key]) is not kind:
            raise ProtocolError(BAD_REQUEST, f"'{key}' must be a {kind.__name__}, got {show(doc[key])}", rid)
    if "session" in doc and not (0 < len(doc["session"]) <= 64):
        raise ProtocolError(BAD_REQUEST, "'session' must be a token of 1-64 characters", rid)
    return doc


def ok_reply(request_id, **fields) -> dict[str, Any]:
    return {"protocol": PROTOCOL, "version": VERSION, "id": request_id, "ok": True, **fields}


def error_reply(request_id, code: str, message: str) -> dict[str, Any]:
    return {"protocol": PROTOCOL, "version": VERSION, "id": echo_id(request_id), "ok": False,
            "error": {"code": code, "message": message}}


def encode_error(request_id, code: str, message: str) -> bytes:
    """An error reply that always encodes (the id is sanitised, the message made ASCII-safe)."""
    try:
        return encode(error_reply(request_id, code, message))
    except (ValueError, TypeError):
        return encode(error_reply(None, code, message.encode("ascii", "replace").decode()))


# --- payloads ---------------------------------------------------------------------------------------
def command_to_wire(cmd: Command) -> dict[str, Any]:
    return {"b_static_T": [float(cmd.b_static[0]), float(cmd.b_static[1])], "b_osc_T": float(cmd.b_osc),
            "freq_Hz": float(cmd.freq)}


def command_from_wire(doc: Any) -> Command:
    """Validate a ``cmd`` object (shape, types, finiteness); limits are checked by the rig."""
    if not isinstance(doc, dict):
        raise ProtocolError(BAD_REQUEST, "'cmd' must be an object with b_static_T, b_osc_T, freq_Hz")
    missing = [k for k in ("b_static_T", "b_osc_T", "freq_Hz") if k not in doc]
    if missing:
        raise ProtocolError(BAD_REQUEST, f"'cmd' lacks {missing}")
    bs, bo, fr = doc["b_static_T"], doc["b_osc_T"], doc["freq_Hz"]
    extra = sorted(set(doc) - {"b_static_T", "b_osc_T", "freq_Hz"})
    if extra:
        raise ProtocolError(BAD_REQUEST, f"'cmd' has unknown fields {show(extra)}")
    if not (isinstance(bs, list) and len(bs) == 2 and all(_is_number(x) for x in bs)):
        raise ProtocolError(BAD_COMMAND, f"b_static_T must be a list of 2 finite numbers, got {show(bs)}")
    for name, v in (("b_osc_T", bo), ("freq_Hz", fr)):
        if not _is_number(v):
            raise ProtocolError(BAD_COMMAND, f"{name} must be a finite number, got {show(v)}")
    try:
        return Command.from_values(bs, bo, fr)
    except CommandRejected as err:
        raise ProtocolError(BAD_COMMAND, str(err)) from None


def _is_number(x) -> bool:
    """A finite JSON number that converts to a finite float64 (not a boolean, not a huge integer)."""
    if type(x) is float:
        return x == x and abs(x) != float("inf")
    if type(x) is int:
        return abs(x) < 1e300
    return False


def observation_to_wire(obs: Observation) -> dict[str, Any]:
    return {
        "t_s": obs.t, "frame": obs.frame,
        "robot_est_m": obs.robot_est.tolist(), "heading_est_rad": obs.heading_est,
        "spheres_est_m": obs.spheres_est.tolist(), "lost": obs.lost, "currents_A": obs.currents.tolist(),
    }


def observation_from_wire(doc: dict[str, Any]) -> Observation:
    try:
        spheres = np.asarray(doc["spheres_est_m"], dtype=float).reshape(-1, 2)
        return Observation(
            t=float(doc["t_s"]), frame=int(doc["frame"]),
            robot_est=np.asarray(doc["robot_est_m"], dtype=float).reshape(2),
            heading_est=float(doc["heading_est_rad"]), spheres_est=spheres, lost=bool(doc["lost"]),
            currents=np.asarray(doc.get("currents_A", [0.0] * 6), dtype=float).reshape(6),
        )
    except (KeyError, TypeError, ValueError) as err:
        raise ProtocolError(BAD_REQUEST, f"malformed observation: {err}") from None
