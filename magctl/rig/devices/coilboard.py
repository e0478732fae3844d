"""The coil amplifier board's serial protocol — the one Python definition (no I/O here).

The board's firmware (``firmware/magcoil/magcoil.c``) and :class:`~magctl.rig.devices.serial_board.SerialCoilBoard`
speak it; docs/coil-board.md is the reference. A frame, all fields little-endian::

    A5 5A | type (u8) | seq (u16) | len (u8) | payload (len ≤ 96 bytes) | CRC-16/CCITT-FALSE (u16) of type..payload

Host → board: PING, SET, ZERO, CONFIG, INFO. Board → host: STATUS (reply to PING, SET, ZERO, CONFIG), NAK
(a refused frame, with a reason code), INFO_REPLY. Every reply echoes the request's seq. Currents are signed
microamps (int32), frequencies millihertz (uint32), times microseconds (uint32).

This module encodes and decodes frames and payloads, computes the CRC and offers :class:`StreamDecoder`, a
resynchronising byte-stream parser that follows the firmware's rules exactly.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

import numpy as np

SYNC = b"\xa5\x5a"
VERSION = 1
HEADER = 6
"""Bytes before the payload: sync (2), type, seq (2), len."""
MAX_PAYLOAD = 96
MAX_FRAME = HEADER + MAX_PAYLOAD + 2
N_CHANNELS = 6

# frame types
PING, SET, ZERO, CONFIG, INFO = 0x01, 0x02, 0x03, 0x04, 0x05
STATUS, NAK, INFO_REPLY = 0x81, 0x82, 0x85
TYPE_NAMES = {PING: "PING", SET: "SET", ZERO: "ZERO", CONFIG: "CONFIG", INFO: "INFO",
              STATUS: "STATUS", NAK: "NAK", INFO_REPLY: "INFO_REPLY"}

# NAK reason codes
R_BAD_LENGTH, R_UNKNOWN_TYPE, R_STALE_SEQ, R_OVER_RATING, R_FREQ_RANGE, R_DEADLINE_RANGE = 1, 2, 3, 4, 5, 6
REASONS = {R_BAD_LENGTH: "payload length wrong for the frame type",
           R_UNKNOWN_TYPE: "unknown frame type",
           R_STALE_SEQ: "sequence number not newer than the last accepted",
           R_OVER_RATING: "peak current |dc|+|ac| over the channel's rating",
           R_FREQ_RANGE: "frequency above the board's maximum",
           R_DEADLINE_RANGE: "deadline 0 or above the board's maximum"}

# STATUS flags
F_TRIPPED, F_ARMED = 0x01, 0x02

# firmware defaults (magcoil.h), for a board built without -D overrides
DEFAULT_RATINGS_UA = (3_000_000, 3_000_000, 3_000_000, 3_000_000, 2_000_000, 2_000_000)
DEFAULT_FREQ_MAX_MHZ = 1_000_000
DEFAULT_DEADLINE_MAX_US = 500_000
DEFAULT_DEADLINE_US = 100_000

_SET = struct.Struct(f"<{N_CHANNELS}i{N_CHANNELS}iI")
_STATUS = struct.Struct(f"<BBHII{N_CHANNELS}i{N_CHANNELS}iI6I")
_INFO = struct.Struct(f"<BBH{N_CHANNELS}iIIII")
_NAK = struct.Struct("<BBB")
_U32 = struct.Struct("<I")
SET_LEN, CONFIG_LEN = _SET.size, 4
STATUS_LEN, NAK_LEN, INFO_LEN = _STATUS.size, _NAK.size, _INFO.size
COUNTER_NAMES = ("frames_ok", "crc_errors", "malformed", "rejected", "deadline_trips", "tx_dropped")


class ProtocolError(ValueError):
    """A payload that does not decode (wrong length for its type)."""


# --- CRC and frames -------------------------------------------------------------------------------
def _crc_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
        table.append(crc)
    return tuple(table)


_TABLE = _crc_table()


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, not reflected, no final xor) of ``data``."""
    crc = 0xFFFF
    for b in data:
        crc = ((crc << 8) & 0xFFFF) ^ _TABLE[((crc >> 8) ^ b) & 0xFF]
    return crc


@dataclass(frozen=True)
class Frame:
    """One decoded frame: its type, sequence number and payload bytes."""

    type: int
    seq: int
    payload: bytes = b""

    @property
    def name(self) -> str:
        return TYPE_NAMES.get(self.type, f"0x{self.type:02x}")


def encode_frame(ftype: int, seq: int, payload: bytes = b"") -> bytes:
    """The bytes of one frame: sync, header, payload and CRC (seq taken modulo 2^16)."""
    if len(payload) > MAX_PAYLOAD:
        raise ProtocolError(f"payload of {len(payload)} bytes exceeds {MAX_PAYLOAD}")
    body = struct.pack("<BHB", ftype & 0xFF, seq & 0xFFFF, len(payload)) + bytes(payload)
    return SYNC + body + struct.pack("<H", crc16(body))


class StreamDecoder:
    """A resynchronising parser of a byte stream, the firmware's rules in Python.

    :meth:`feed` returns the complete frames found. A false sync — a length above :data:`MAX_PAYLOAD` or a bad
    CRC — is dropped one byte at a time, so the bytes after it are rescanned and a real frame behind it is
    still found. :meth:`expire` gives up on a partial frame (the firmware does so after a gap of silence).
    Counters: ``crc_errors``, ``malformed``, ``frames``.
    """

    def __init__(self):
        self._buf = bytearray()
        self.crc_errors = 0
        self.malformed = 0
        self.frames = 0

    @property
    def pending(self) -> int:
        """Bytes held of an incomplete frame."""
        return len(self._buf)

    def feed(self, data: bytes) -> list[Frame]:
        """Append ``data``; the frames it completes, in order."""
        self._buf += data
        return self._parse()

    def expire(self) -> list[Frame]:
        """Drop the partial frame held (byte by byte, rescanning the rest); the complete frames found behind it."""
        out = []
        if self._buf:
            self.malformed += 1
        while self._buf:
            del self._buf[0]
            out += self._parse()
        return out

    def _parse(self) -> list[Frame]:
        out = []
        buf = self._buf
        while buf:
            if buf[0] != SYNC[0]:
                i = buf.find(SYNC[:1])
                del buf[:i if i >= 0 else len(buf)]
                continue
            if len(buf) < 2:
                break
            if buf[1] != SYNC[1]:
                del buf[0]
                continue
            if len(buf) < HEADER:
                break
            n = buf[5]
            if n > MAX_PAYLOAD:
                self.malformed += 1
                del buf[0]
                continue
            total = HEADER + n + 2
            if len(buf) < total:
                break
            if crc16(bytes(buf[2:HEADER + n])) != int.from_bytes(buf[HEADER + n:total], "little"):
                self.crc_errors += 1
                del buf[0]
                continue
            out.append(Frame(buf[2], int.from_bytes(buf[3:5], "little"), bytes(buf[HEADER:HEADER + n])))
            self.frames += 1
            del buf[:total]
        return out


def seq_newer(seq: int, last: int) -> bool:
    """The firmware's sequence rule (RFC 1982 on 16 bits): ``seq`` is newer than ``last`` when
    ``0 < (seq - last) mod 2^16 < 2^15``."""
    d = (seq - last) & 0xFFFF
    return 0 < d < 0x8000


# --- payloads -------------------------------------------------------------------------------------
def set_payload(dc_ua, ac_ua, freq_mhz: int) -> bytes:
    """SET payload: six int32 static currents (µA), six int32 amplitudes (µA), uint32 frequency (mHz)."""
    dc = [int(v) for v in dc_ua]
    ac = [int(v) for v in ac_ua]
    if len(dc) != N_CHANNELS or len(ac) != N_CHANNELS:
        raise ProtocolError(f"a SET carries {N_CHANNELS} static currents and {N_CHANNELS} amplitudes")
    return _SET.pack(*dc, *ac, int(freq_mhz))


def config_payload(deadline_us: int) -> bytes:
    """CONFIG payload: the deadline, uint32 µs (the board refuses 0 and values above its maximum)."""
    return _U32.pack(int(deadline_us))


def decode_set(payload: bytes) -> tuple[tuple[int, ...], tuple[int, ...], int]:
    """(dc µA, ac µA, freq mHz) of a SET payload."""
    if len(payload) != SET_LEN:
        raise ProtocolError(f"SET payload is {len(payload)} bytes, not {SET_LEN}")
    v = _SET.unpack(payload)
    return v[:N_CHANNELS], v[N_CHANNELS:2 * N_CHANNELS], v[-1]


@dataclass(frozen=True)
class Status:
    """A STATUS reply: the board's outputs, deadline state and counters.

    ``since_set_us`` is the time since the last accepted SET while the outputs are on (None otherwise);
    ``last_seq`` the seq of the last accepted SET or CONFIG.
    """

    seq: int
    tripped: bool
    armed: bool
    last_seq: int
    deadline_us: int
    since_set_us: int | None
    dc_ua: tuple[int, ...]
    ac_ua: tuple[int, ...]
    freq_mhz: int
    counters: dict = field(default_factory=dict)

    @property
    def dc(self) -> np.ndarray:
        """Static currents, A."""
        return np.asarray(self.dc_ua, dtype=float) * 1e-6

    @property
    def ac(self) -> np.ndarray:
        """Sine amplitudes, A."""
        return np.asarray(self.ac_ua, dtype=float) * 1e-6

    @property
    def freq(self) -> float:
        """Sine frequency, Hz."""
        return self.freq_mhz * 1e-3

    def is_zero(self) -> bool:
        return not (any(self.dc_ua) or any(self.ac_ua))


def decode_status(frame: Frame) -> Status:
    """The :class:`Status` of a STATUS frame."""
    if len(frame.payload) != STATUS_LEN:
        raise ProtocolError(f"STATUS payload is {len(frame.payload)} bytes, not {STATUS_LEN}")
    v = _STATUS.unpack(frame.payload)
    flags, _n, last_seq, deadline, since = v[:5]
    dc, ac = v[5:5 + N_CHANNELS], v[5 + N_CHANNELS:5 + 2 * N_CHANNELS]
    freq = v[5 + 2 * N_CHANNELS]
    counters = dict(zip(COUNTER_NAMES, v[6 + 2 * N_CHANNELS:]))
    return Status(frame.seq, bool(flags & F_TRIPPED), bool(flags & F_ARMED), last_seq, deadline,
                  None if since == 0xFFFFFFFF else since, dc, ac, freq, counters)


def status_payload(s: Status) -> bytes:
    """The payload of a STATUS (for simulated boards and tests)."""
    flags = (F_TRIPPED if s.tripped else 0) | (F_ARMED if s.armed else 0)
    since = 0xFFFFFFFF if s.since_set_us is None else s.since_set_us
    return _STATUS.pack(flags, N_CHANNELS, s.last_seq, s.deadline_us, since, *s.dc_ua, *s.ac_ua, s.freq_mhz,
                        *(int(s.counters.get(k, 0)) for k in COUNTER_NAMES))


@dataclass(frozen=True)
class Nak:
    """A NAK reply: why the frame ``seq`` of type ``rejected_type`` was refused (``detail``: the channel of an
    over-rating SET, else 0 or the bad length)."""

    seq: int
    reason: int
    detail: int
    rejected_type: int

    def describe(self) -> str:
        what = REASONS.get(self.reason, f"reason {self.reason}")
        if self.reason == R_OVER_RATING:
            what += f" (channel {self.detail})"
        return f"{TYPE_NAMES.get(self.rejected_type, hex(self.rejected_type))} seq {self.seq} refused: {what}"


def decode_nak(frame: Frame) -> Nak:
    if len(frame.payload) != NAK_LEN:
        raise ProtocolError(f"NAK payload is {len(frame.payload)} bytes, not {NAK_LEN}")
    reason, detail, rtype = _NAK.unpack(frame.payload)
    return Nak(frame.seq, reason, detail, rtype)


@dataclass(frozen=True)
class Info:
    """An INFO_REPLY: the firmware's compiled-in limits and its current deadline."""

    version: int
    n_channels: int
    ratings_ua: tuple[int, ...]
    freq_max_mhz: int
    deadline_max_us: int
    deadline_us: int
    rx_gap_us: int


def decode_info(frame: Frame) -> Info:
    if len(frame.payload) != INFO_LEN:
        raise ProtocolError(f"INFO_REPLY payload is {len(frame.payload)} bytes, not {INFO_LEN}")
    v = _INFO.unpack(frame.payload)
    return Info(v[0], v[1], tuple(v[3:3 + N_CHANNELS]), *v[3 + N_CHANNELS:])


# --- units ----------------------------------------------------------------------------------------
def amps_to_ua(dc: np.ndarray, ac: np.ndarray, ratings_ua) -> tuple[list[int], list[int]]:
    """Currents in A → integer µA, rounded to nearest; a channel whose rounded peak would exceed its rating by
    rounding is truncated towards zero instead (never above a rating that the unrounded setpoint respected)."""
    dc_ua = np.rint(np.asarray(dc, dtype=float) * 1e6)
    ac_ua = np.rint(np.asarray(ac, dtype=float) * 1e6)
    over = np.abs(dc_ua) + np.abs(ac_ua) > np.asarray(ratings_ua, dtype=float)
    dc_ua[over] = np.trunc(np.asarray(dc, dtype=float)[over] * 1e6)
    ac_ua[over] = np.trunc(np.asarray(ac, dtype=float)[over] * 1e6)
    return [int(v) for v in dc_ua], [int(v) for v in ac_ua]


def hz_to_mhz(freq: float) -> int:
    """Frequency in Hz → integer mHz (rounded)."""
    return int(round(float(freq) * 1e3))
