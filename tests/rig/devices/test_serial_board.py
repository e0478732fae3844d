"""SerialCoilBoard, the pyserial adapter of the coil board: the contract test on the C firmware behind its pty,
missing ports, boards with other ratings, sequence wrap, and links that corrupt, repeat or drop bytes — each
ends in a working driver or a DeviceError naming the device, never a traceback or a hang."""

from __future__ import annotations

import os
import select
import threading
import tty

import numpy as np
import pytest

from magctl.rig.devices.base import CoilSetpoint, DeviceError
from magctl.rig.devices.contract import check_coil_driver
from magctl.rig.devices.firmware import HostBoard, build_host, defines
from magctl.rig.devices.serial_board import SerialCoilBoard
from magctl.rig.interface import CommandRejected

GOOD = CoilSetpoint([1.0, -1.0, 0.5, 0.0, 1.2, 0.0], [0.0, 0.1, 0.0, -0.3, 0.0, 0.2], 20.0)


class Relay:
    """A pty pair between the adapter and the board's pty; every chunk passes through
    ``transform(direction, offset, data) -> bytes`` (direction "up": adapter → board, "down": board → adapter;
    offset: bytes of that direction before this chunk)."""

    def __init__(self, board_pty: str, transform):
        self.master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.path = os.ttyname(self._slave)
        self.board = os.open(board_pty, os.O_RDWR | os.O_NOCTTY)
        tty.setraw(self.board)
        self.transform = transform
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self):
        route = {self.master: (self.board, "up"), self.board: (self.master, "down")}
        offset = {"up": 0, "down": 0}
        while not self._stop.is_set():
            for fd in select.select(list(route), [], [], 0.02)[0]:
                try:
                    data = os.read(fd, 4096)
                except OSError:
                    continue
                dst, d = route[fd]
                out = self.transform(d, offset[d], data)
                offset[d] += len(data)
                if out:
                    os.write(dst, out)

    def close(self):
        self._stop.set()
        self._thread.join(timeout=5)
        for fd in (self.master, self._slave, self.board):
            os.close(fd)


def flip_at(direction: str, positions: set[int]):
    """Flip bit 3 of the bytes at ``positions`` of one direction's stream."""
    def transform(d, offset, data):
        if d != direction:
            return data
        return bytes(b ^ 0x08 if d == direction and offset + i in positions else b for i, b in enumerate(data))
    return transform


# --- the contract -----------------------------------------------------------------------------------
def test_contract_on_the_firmware_behind_its_pty(board):
    """check_coil_driver with the board's clock driven by the test: open at zero, apply, refuse, zero, and the
    device-side deadline one deadline after the last setpoint."""
    check_coil_driver(lambda: SerialCoilBoard(board.pty), wait=board.advance)
    out = board.outputs()
    assert out.is_zero() and out.counters["deadline_trips"] == 1


def test_contract_through_a_relay_that_repeats_every_reply(board):
    """Every reply is preceded by a copy of the one before: the copies carry old seqs and are skipped."""
    previous = [b""]

    def transform(d, offset, data):
        if d != "down":
            return data
        out, previous[0] = previous[0] + data, data
        return out

    relay = Relay(board.pty, transform)
    try:
        check_coil_driver(lambda: SerialCoilBoard(relay.path), wait=board.advance)
    finally:
        relay.close()


# --- opening --------------------------------------------------------------------------------------
def test_a_missing_port_names_the_device_and_the_port():
    drv = SerialCoilBoard("/dev/ttyMAGCOIL-NOT-THERE", name="coils-A")
    with pytest.raises(DeviceError, match=r"^coils-A: cannot open serial port /dev/ttyMAGCOIL-NOT-THERE") as err:
        drv.open()
    assert err.value.device == "coils-A"
    with pytest.raises(DeviceError, match="not open"):
        drv.write(GOOD)
    drv.close()


def test_a_pyserial_url_without_a_board_is_a_device_error():
    """``loop://`` echoes the adapter's own frames: requests, never replies — a silent board."""
    drv = SerialCoilBoard("loop://", reply_timeout=0.05)
    with pytest.raises(DeviceError, match=r"^coil-board: loop://: no valid reply to ZERO in 3 tries"):
        drv.open()
    drv.close()


def test_a_deadline_above_the_boards_maximum_is_refused_at_open(board):
    drv = SerialCoilBoard(board.pty, deadline=0.6)
    with pytest.raises(DeviceError, match=r"deadline 0.6 s is outside the board's \(0, 0.5\] s"):
        drv.open()
    with pytest.raises(DeviceError, match="not open"):
        drv.zero()
    with SerialCoilBoard(board.pty, deadline=0.5) as ok:
        assert ok.ping().deadline_us == 500_000


def test_the_boards_own_ratings_lower_the_adapters(tmp_path):
    exe = build_host(tmp_path, defines(ratings=[1, 1, 1, 1, 0.5, 0.5], freq_max=200.0))
    with HostBoard(exe=str(exe)) as b, SerialCoilBoard(b.pty) as drv:
        np.testing.assert_array_equal(drv.current_limit, [1, 1, 1, 1, 0.5, 0.5])
        assert drv.freq_max == 200.0 and drv.info.ratings_ua == (1_000_000,) * 4 + (500_000,) * 2
        frames = drv.ping().counters["frames_ok"]
        for sp in (CoilSetpoint([0, 0, 0, 0, 0.6, 0], np.zeros(6), 1.0),
                   CoilSetpoint(np.zeros(6), np.zeros(6), 201.0)):
            with pytest.raises(CommandRejected, match="^coil-board: "):
                drv.write(sp)
        st = drv.ping()                                      # nothing was sent
        assert st.counters["frames_ok"] == frames + 1 and st.counters["rejected"] == 0
        drv.write(CoilSetpoint([1, -1, 0, 0, 0.25, 0], [0, 0, 0, 0, -0.25, 0], 200.0))
        assert b.outputs().dc[0] == 1.0


# --- sequence numbers -------------------------------------------------------------------------------
def test_the_adapters_seq_wraps(board):
    with SerialCoilBoard(board.pty, first_seq=65_532) as drv:   # ZERO, INFO, CONFIG take 65532..65534
        for k in range(5):                                      # SETs 65535, 0, 1, 2, 3
            drv.write(CoilSetpoint(GOOD.dc * (k + 1) / 5, GOOD.ac, GOOD.freq))
            assert drv.last_status.last_seq == (65_535 + k) & 0xFFFF
        assert board.outputs().counters["rejected"] == 0
        np.testing.assert_allclose(board.outputs().dc, GOOD.dc, atol=1e-6)


def test_a_second_session_starts_a_new_seq_window(board):
    """A reopened adapter starts at seq 0 again; its CONFIG opens a new window on the board."""
    with SerialCoilBoard(board.pty, first_seq=30_000) as drv:
        drv.write(GOOD)
    with SerialCoilBoard(board.pty) as drv:
        drv.write(GOOD)
        assert drv.readback().setpoint.dc[0] == 1.0


# --- corrupting links ------------------------------------------------------------------------------
def test_a_corrupted_reply_is_dropped_and_the_request_retried(board):
    """Bit 3 of one byte inside the SET's STATUS flipped: the reply fails its CRC, the adapter sends the SET
    again with a fresh seq and gets it confirmed (the board applied both: same outputs)."""
    # replies before the SET's: STATUS (96 bytes, ZERO), INFO_REPLY (52), STATUS (96, CONFIG)
    relay = Relay(board.pty, flip_at("down", {96 + 52 + 96 + 50}))
    try:
        with SerialCoilBoard(relay.path, reply_timeout=0.1) as drv:
            drv.write(GOOD)
            assert drv._decoder.crc_errors == 1
            rb = drv.readback()
            np.testing.assert_allclose(rb.setpoint.dc, GOOD.dc, atol=1e-6)
            assert rb.counters["frames_ok"] == 6 and rb.counters["crc_errors"] == 0
    finally:
        relay.close()


def test_a_corrupted_request_is_dropped_by_the_board_and_retried(board):
    relay = Relay(board.pty, flip_at("up", {8 + 8 + 12 + 20}))   # inside the first SET (after ZERO, INFO, CONFIG)
    try:
        with SerialCoilBoard(relay.path, reply_timeout=0.1) as drv:
            drv.write(GOOD)
            assert drv.readback().counters["crc_errors"] == 1
    finally:
        relay.close()


def test_a_link_that_keeps_corrupting_is_a_device_error(board):
    """Every 7th byte flipped both ways: no frame survives; open ends in a DeviceError naming the device and the
    port with the CRC error count — after 3 tries of reply_timeout, not a hang."""
    relay = Relay(board.pty, lambda d, offset, data: bytes(
        b ^ 0x01 if (offset + i) % 7 == 3 else b for i, b in enumerate(data)))
    try:
        drv = SerialCoilBoard(relay.path, name="coils-B", reply_timeout=0.05)
        with pytest.raises(DeviceError, match=r"^coils-B: .*no valid reply to ZERO in 3 tries .*CRC errors"):
            drv.open()
        drv.close()
    finally:
        relay.close()


def test_a_link_that_goes_bad_mid_run_ends_in_a_device_error_and_the_board_zeroes(board):
    bad = threading.Event()

    def transform(d, offset, data):
        return bytes(b ^ 0xFF for b in data) if bad.is_set() else data

    relay = Relay(board.pty, transform)
    try:
        drv = SerialCoilBoard(relay.path, reply_timeout=0.05)
        drv.open()
        drv.write(GOOD)
        bad.set()
        for call in (lambda: drv.write(GOOD), drv.readback, drv.zero):
            with pytest.raises(DeviceError, match=r"^coil-board: .*no valid reply"):
                call()
        drv.close()                                  # best effort, no exception
        drv.close()
        out = board.advance(0.1)                     # the board does not need the host
        assert out.is_zero() and out.tripped
    finally:
        relay.close()


def test_noise_between_replies_is_skipped(board):
    """Noise and false syncs injected before every reply: the decoder resynchronises, every call succeeds."""
    rng = np.random.default_rng(7)

    def transform(d, offset, data):
        if d != "down":
            return data
        noise = rng.integers(0, 256, 30, dtype=np.uint8).tobytes().replace(b"\xa5", b"\x00")
        return noise + b"\xa5\x5a\x81\x00\x00\xff" + b"\xa5" + data

    relay = Relay(board.pty, transform)
    try:
        with SerialCoilBoard(relay.path, reply_timeout=0.2) as drv:
            for k in range(5):
                drv.write(CoilSetpoint(GOOD.dc * k / 5, GOOD.ac, GOOD.freq))
            assert drv.readback().counters["rejected"] == 0
            assert drv._decoder.malformed >= 5
    finally:
        relay.close()


def test_close_zeroes_the_outputs(board):
    drv = SerialCoilBoard(board.pty)
    drv.open()
    drv.write(GOOD)
    assert not board.outputs().is_zero()
    drv.close()
    out = board.outputs()
    assert out.is_zero() and not out.tripped
    with pytest.raises(DeviceError, match="not open"):
        drv.write(GOOD)
