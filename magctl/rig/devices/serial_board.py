"""The coil amplifier board over a serial port: :class:`SerialCoilBoard`, a :class:`CoilDriver` on pyserial.

The board runs ``firmware/magcoil`` (protocol: :mod:`magctl.rig.devices.coilboard`, docs/coil-board.md) and
enforces the deadline itself: with no accepted SET for :attr:`~SerialCoilBoard.deadline` s its outputs go to
zero, whatever this computer does — a killed, frozen or babbling host cannot keep the coils on, and neither can
a heartbeat (:meth:`~SerialCoilBoard.ping` is answered but does not restart the deadline).

Every request is answered by a frame echoing its sequence number (STATUS, NAK or INFO_REPLY). Replies with
another seq are stale and skipped; corrupted bytes are dropped by the resynchronising decoder. A request without
a valid reply within ``reply_timeout`` is sent again with a fresh seq (safe for every type: a repeated SET applies
the same outputs); after ``attempts`` tries the call raises :class:`DeviceError` naming the board and the port —
a dead or corrupting link ends in an error, never in a hang.
"""

from __future__ import annotations

import threading
import time

import numpy as np

from magctl.rig.devices import coilboard as cb
from magctl.rig.devices.base import CoilDriver, CoilReadback, CoilSetpoint, DeviceError


class SerialCoilBoard(CoilDriver):
    """The magcoil board behind ``port``: a device path (``/dev/ttyACM0``, a pty) or a pyserial URL (``loop://``,
    ``socket://host:port``, ``rfc2217://...``).

    Parameters
    ----------
    port : str
        Serial device or pyserial URL.
    baudrate : int
        Line speed (ignored by USB CDC boards and ptys).
    deadline : float
        The board's deadline, s, set by CONFIG at :meth:`open` (the firmware refuses 0 and values above its
        compiled maximum, 0.5 s by default).
    current_limit : array_like, optional
        Ratings, A (default: the firmware's defaults, 3 A in-plane and 2 A vertical). At :meth:`open` each is
        lowered to the board's own compiled rating where that is smaller.
    freq_max : float, optional
        Highest frequency, Hz (default the firmware's 1000 Hz; lowered to the board's at :meth:`open`).
    reply_timeout : float
        Seconds to wait for each reply; ``attempts`` tries per request.
    """

    device_deadline = True

    def __init__(self, port: str, *, baudrate: int = 115200, deadline: float = 0.1, current_limit=None,
                 freq_max: float | None = None, name: str = "coil-board", reply_timeout: float = 0.25,
                 attempts: int = 3, first_seq: int = 0):
        if not deadline > 0:
            raise ValueError("deadline must be > 0 s")
        self.port = str(port)
        self.name = name
        self.baudrate = int(baudrate)
        self.deadline = float(deadline)
        self.n_channels = cb.N_CHANNELS
        limit = (np.asarray(cb.DEFAULT_RATINGS_UA, dtype=float) * 1e-6 if current_limit is None
                 else np.asarray(current_limit, dtype=float).reshape(-1))
        if limit.shape != (self.n_channels,):
            raise ValueError(f"current_limit must be {self.n_channels} ratings")
        self.current_limit = limit
        self.freq_max = float(cb.DEFAULT_FREQ_MAX_MHZ * 1e-3 if freq_max is None else freq_max)
        self.reply_timeout = float(reply_timeout)
        self.attempts = max(1, int(attempts))
        self.info: cb.Info | None = None
        """The board's compiled limits (INFO_REPLY), after :meth:`open`."""
        self.last_status: cb.Status | None = None
        self._seq = int(first_seq) & 0xFFFF
        self._ser = None
        self._decoder = cb.StreamDecoder()
        self._lock = threading.RLock()

    # --- CoilDriver -------------------------------------------------------------------------------
    def open(self) -> None:
        """Open the port, then ZERO (outputs off), INFO (the board's ratings) and CONFIG (the deadline), each
        confirmed by the board. A missing port, a silent board or a refusal raises :class:`DeviceError`."""
        try:
            import serial  # pyserial: only this adapter needs it
        except ImportError:
            raise DeviceError(self.name, "pyserial is not installed: pip install 'magctl[hardware]'") from None

        with self._lock:
            if self._ser is not None:
                return
            try:
                self._ser = serial.serial_for_url(self.port, baudrate=self.baudrate, timeout=0.01,
                                                  write_timeout=max(self.reply_timeout, 0.1))
            except (serial.SerialException, OSError, ValueError) as err:
                raise DeviceError(self.name, f"cannot open serial port {self.port}: {err}") from None
            try:
                self._ser.reset_input_buffer()
                self._decoder = cb.StreamDecoder()
                self.zero()
                info = self._request(cb.INFO)
                if info.type != cb.INFO_REPLY:
                    raise DeviceError(self.name, f"{self.port}: INFO answered by {info.name}")
                self.info = self._decode(cb.decode_info, info)
                if self.info.n_channels != self.n_channels:
                    raise DeviceError(self.name, f"{self.port}: the board has {self.info.n_channels} channels, "
                                                 f"not {self.n_channels}")
                board_limit = np.asarray(self.info.ratings_ua, dtype=float) * 1e-6
                self.current_limit = np.minimum(self.current_limit, board_limit)
                self.freq_max = min(self.freq_max, self.info.freq_max_mhz * 1e-3)
                deadline_us = int(round(self.deadline * 1e6))
                if not 0 < deadline_us <= self.info.deadline_max_us:
                    raise DeviceError(self.name, f"{self.port}: deadline {self.deadline:g} s is outside the "
                                                 f"board's (0, {self.info.deadline_max_us * 1e-6:g}] s")
                st = self._status(cb.CONFIG, cb.config_payload(deadline_us))
                if st.deadline_us != deadline_us:
                    raise DeviceError(self.name, f"{self.port}: board reports deadline {st.deadline_us} us after "
                                                 f"CONFIG {deadline_us} us")
            except BaseException:
                self._close_port()
                raise

    def write(self, setpoint: CoilSetpoint) -> None:
        """SET ``setpoint``: checked against the ratings first (:class:`CommandRejected`, nothing sent), quantised
        to µA and mHz, sent with the next seq; the board's STATUS must echo exactly the outputs sent, else
        :class:`DeviceError` (also on a NAK or no reply)."""
        with self._lock:
            self._require_open()
            setpoint.check(self.current_limit, self.freq_max, self.name)
            dc, ac = cb.amps_to_ua(setpoint.dc, setpoint.ac, np.rint(self.current_limit * 1e6))
            f = cb.hz_to_mhz(setpoint.freq)
            st = self._status(cb.SET, cb.set_payload(dc, ac, f))
            if list(st.dc_ua) != dc or list(st.ac_ua) != ac or (st.freq_mhz != f and not st.is_zero()):
                raise DeviceError(self.name, f"{self.port}: board reports outputs {st.dc_ua} {st.ac_ua} "
                                             f"{st.freq_mhz} mHz after SET {dc} {ac} {f} mHz")

    def zero(self) -> None:
        """ZERO: all outputs off at once (accepted by the board whatever the seq); confirmed by its STATUS."""
        with self._lock:
            self._require_open()
            st = self._status(cb.ZERO)
            if not st.is_zero():
                raise DeviceError(self.name, f"{self.port}: outputs not zero after ZERO")

    def readback(self) -> CoilReadback:
        """The board's outputs, trip flag and counters (a PING; it does not restart the deadline)."""
        st = self.ping()
        return CoilReadback(CoilSetpoint(st.dc, st.ac, st.freq), st.tripped,
                            {**st.counters, "since_set_us": st.since_set_us})

    def ping(self) -> cb.Status:
        """Heartbeat: PING → the board's STATUS. Shows the link is alive; does NOT keep the outputs on (only an
        accepted SET restarts the deadline)."""
        with self._lock:
            self._require_open()
            return self._status(cb.PING)

    def close(self) -> None:
        """ZERO (best effort, one try) and close the port; idempotent."""
        with self._lock:
            if self._ser is None:
                return
            try:
                self._status(cb.ZERO, attempts=1)
            except DeviceError:
                pass
            finally:
                self._close_port()

    # --- transactions -----------------------------------------------------------------------------
    def _require_open(self) -> None:
        if self._ser is None:
            raise DeviceError(self.name, f"{self.port}: not open")

    def _close_port(self) -> None:
        ser, self._ser = self._ser, None
        if ser is not None:
            try:
                ser.close()
            except Exception:  # noqa: BLE001 - releasing a broken port must not raise
                pass

    def _decode(self, fn, frame: cb.Frame):
        try:
            return fn(frame)
        except cb.ProtocolError as err:
            raise DeviceError(self.name, f"{self.port}: {err}") from None

    def _status(self, ftype: int, payload: bytes = b"", attempts: int | None = None) -> cb.Status:
        """Send a request answered by STATUS; a NAK or another reply type is a :class:`DeviceError`."""
        frame = self._request(ftype, payload, attempts)
        if frame.type == cb.NAK:
            nak = self._decode(cb.decode_nak, frame)
            raise DeviceError(self.name, f"{self.port}: {nak.describe()}")
        if frame.type != cb.STATUS:
            raise DeviceError(self.name, f"{self.port}: {cb.TYPE_NAMES[ftype]} answered by {frame.name}")
        st = self._decode(cb.decode_status, frame)
        self.last_status = st
        return st

    def _request(self, ftype: int, payload: bytes = b"", attempts: int | None = None) -> cb.Frame:
        """Send one request and return the reply echoing its seq; retried with a fresh seq on silence."""
        import serial

        attempts = self.attempts if attempts is None else attempts
        for _ in range(attempts):
            seq = self._seq
            self._seq = (self._seq + 1) & 0xFFFF
            try:
                self._ser.write(cb.encode_frame(ftype, seq, payload))
            except (serial.SerialException, OSError) as err:
                raise DeviceError(self.name, f"{self.port}: write failed: {err}") from None
            reply = self._await(seq)
            if reply is not None:
                return reply
        d = self._decoder
        raise DeviceError(self.name, f"{self.port}: no valid reply to {cb.TYPE_NAMES[ftype]} in {attempts} "
                                     f"tries of {self.reply_timeout:g} s (link: {d.crc_errors} CRC errors, "
                                     f"{d.malformed} malformed frames)")

    def _await(self, seq: int) -> cb.Frame | None:
        """The first reply frame with ``seq`` read within :attr:`reply_timeout`; stale replies are skipped."""
        import serial

        replies = (cb.STATUS, cb.NAK, cb.INFO_REPLY)
        end = time.monotonic() + self.reply_timeout
        while True:
            try:
                data = self._ser.read(max(1, self._ser.in_waiting))
            except (serial.SerialException, OSError) as err:
                raise DeviceError(self.name, f"{self.port}: read failed: {err}") from None
            frames = self._decoder.feed(data) if data else []
            if time.monotonic() >= end:
                frames += self._decoder.expire()   # a false sync must not swallow the next reply
            for f in frames:
                if f.seq == seq and f.type in replies:
                    return f
            if time.monotonic() >= end:
                return None
