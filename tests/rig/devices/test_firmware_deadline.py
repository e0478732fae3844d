"""The coil board's own deadline and safety rules, on the C firmware behind its pty with the test's clock.

The board's clock moves only when the test says (``--clock external``), so every assertion is exact: the
outputs are on one microsecond before the deadline after the last valid SET and off at the deadline (well
within deadline + one 1/30 s frame), whatever the host does — killed, frozen, heartbeat-only, or flooding the
link with noise, malformed, corrupted, stale and refused frames. Wall-clock timeouts are hang guards only.
"""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
import time
import tty
from pathlib import Path

import numpy as np
import pytest

from magctl.rig.devices import coilboard as cb
from magctl.rig.devices.firmware import HostBoard, build_host, defines

ROOT = Path(__file__).resolve().parents[3]
FRAME_US = 33_333            # one camera frame, 1/30 s
DEADLINE_US = 100_000        # the adapter's default deadline, 0.1 s
DC = (1_000_000, -1_000_000, 500_000, 0, 1_200_000, 0)
AC = (0, 100_000, 0, -300_000, 0, 200_000)


class Link:
    """The board's serial port opened raw by the test; replies matched by seq, hang-guarded."""

    def __init__(self, path: str):
        self.fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        tty.setraw(self.fd)
        self.dec = cb.StreamDecoder()
        self.pending: list[cb.Frame] = []
        self.sync_seq = 0xE000

    def send(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            select.select([], [self.fd], [], 1.0)
            view = view[os.write(self.fd, view):]

    def reply(self, seq: int, timeout: float = 5.0) -> cb.Frame | None:
        end = time.monotonic() + timeout
        while True:
            while self.pending:
                f = self.pending.pop(0)
                if f.seq == seq and f.type in (cb.STATUS, cb.NAK, cb.INFO_REPLY):
                    return f
            if time.monotonic() >= end:
                return None
            if select.select([self.fd], [], [], 0.02)[0]:
                self.pending += self.dec.feed(os.read(self.fd, 65536))

    def request(self, ftype: int, seq: int, payload: bytes = b"") -> cb.Frame:
        self.send(cb.encode_frame(ftype, seq, payload))
        f = self.reply(seq)
        assert f is not None, f"no reply to {cb.TYPE_NAMES.get(ftype)} seq {seq}"
        return f

    def set(self, seq: int, dc=DC, ac=AC, freq_mhz: int = 20_000) -> cb.Frame:
        return self.request(cb.SET, seq, cb.set_payload(dc, ac, freq_mhz))

    def sync(self) -> None:
        """Every byte sent so far has been processed: a PING answered after them (padding first completes any
        false sync the noise left open; the PING is repeated until one is found)."""
        self.send(b"\x00" * (cb.MAX_FRAME + 8))
        for _ in range(30):
            self.sync_seq = (self.sync_seq + 1) & 0xFFFF
            self.send(cb.encode_frame(cb.PING, self.sync_seq))
            if self.reply(self.sync_seq, timeout=0.3) is not None:
                return
        raise AssertionError("the board never answered a PING after the flood")

    def close(self) -> None:
        os.close(self.fd)


def status(f: cb.Frame) -> cb.Status:
    assert f.type == cb.STATUS, cb.decode_nak(f).describe() if f.type == cb.NAK else f
    return cb.decode_status(f)


def nak(f: cb.Frame) -> cb.Nak:
    assert f.type == cb.NAK, f"expected a NAK, got {f.name}"
    return cb.decode_nak(f)


def assert_outputs(out, dc=DC, ac=AC):
    np.testing.assert_array_equal(np.rint(out.dc * 1e6), dc)
    np.testing.assert_array_equal(np.rint(out.ac * 1e6), ac)


def run_to_deadline(board: HostBoard, t_set: int, deadline_us: int = DEADLINE_US, between=lambda: None,
                    dc=DC, ac=AC) -> None:
    """Advance the board's clock frame by frame from the last valid SET at ``t_set``: the outputs stay as set
    up to deadline − 1 µs, are zero (tripped, one trip, one output-stage call) at the deadline, and stay zero one
    frame later. ``between`` runs before every clock step (the host's misbehaviour)."""
    k = 1
    while k * FRAME_US < deadline_us:
        between()
        out = board.set_clock_us(t_set + k * FRAME_US)
        assert out.armed and not out.tripped, (k, out)
        assert_outputs(out, dc, ac)
        k += 1
    between()
    out = board.set_clock_us(t_set + deadline_us - 1)
    assert out.armed and not out.tripped
    assert_outputs(out, dc, ac)
    trips, writes = out.counters["deadline_trips"], out.output_writes
    between()
    out = board.set_clock_us(t_set + deadline_us)
    assert out.is_zero() and out.freq == 0 and out.tripped and not out.armed, out
    assert out.counters["deadline_trips"] == trips + 1 and out.output_writes == writes + 1
    between()
    out = board.set_clock_us(t_set + deadline_us + FRAME_US)
    assert out.is_zero() and out.tripped and out.counters["deadline_trips"] == trips + 1


# --- the host process that wrote the SET: killed, frozen, or heartbeat only --------------------
CHILD = f"""
import sys, threading, time
from magctl.rig.devices.base import CoilSetpoint
from magctl.rig.devices.serial_board import SerialCoilBoard
port, mode = sys.argv[1], sys.argv[2]
drv = SerialCoilBoard(port, deadline=0.1, reply_timeout=2.0)
drv.open()
drv.write(CoilSetpoint([v * 1e-6 for v in {DC}], [v * 1e-6 for v in {AC}], 20.0))
print("set", flush=True)
if mode == "heartbeat":          # the control loop froze below; its heartbeat thread lives on
    def beat():
        while True:
            drv.ping()
            time.sleep(0.002)
    threading.Thread(target=beat, daemon=True).start()
threading.Event().wait()
"""


@pytest.mark.parametrize("host", ["sigkill", "sigstop", "heartbeat"])
def test_deadline_zeroes_whatever_the_host_process_does(board, host):
    t_set = 1_000_000 if host != "sigstop" else 2**32 - 40_000     # SIGSTOP's window crosses the u32 wrap
    board.set_clock_us(t_set)
    child = subprocess.Popen([sys.executable, "-c", CHILD, board.pty, host], cwd=ROOT, stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE)
    try:
        ready = select.select([child.stdout], [], [], 30.0)[0]
        assert ready and child.stdout.readline() == b"set\n", child.stderr.read() if child.poll() else "no SET"
        out = board.outputs()
        assert out.t_us == t_set and out.armed
        assert_outputs(out)
        between = lambda: None  # noqa: E731
        if host == "sigkill":
            child.send_signal(signal.SIGKILL)
            child.wait(timeout=10)
        elif host == "sigstop":
            child.send_signal(signal.SIGSTOP)
        else:
            def between():
                """A heartbeat arrives in every frame (the board answers it) — and changes nothing."""
                n = board.outputs().counters["frames_ok"]
                end = time.monotonic() + 10.0
                while board.outputs().counters["frames_ok"] <= n:
                    assert time.monotonic() < end and child.poll() is None, "the heartbeat stopped"
                    time.sleep(0.002)
        run_to_deadline(board, t_set, between=between)
    finally:
        child.kill()       # also ends a stopped process
        child.wait(timeout=10)
        child.stdout.close()
        child.stderr.close()


def _flood(link: Link, rng: np.random.Generator, last_seq: int) -> bytes:
    """Everything but a valid, newer, in-rating SET: noise, false syncs, impossible lengths, truncated frames,
    PING/INFO/CONFIG, CRC-broken and bit-flipped newer SETs, stale and duplicate SETs, refused SETs."""
    other = cb.set_payload((2_000_000,) * 4 + (1_000_000,) * 2, (0,) * 6, 1_000)
    newer = (last_seq + 1) & 0xFFFF
    crc_broken = bytearray(cb.encode_frame(cb.SET, newer, other))
    crc_broken[-1] ^= 0x01
    flipped = bytearray(cb.encode_frame(cb.SET, newer, other))
    flipped[10] ^= 0x04
    parts = [
        rng.integers(0, 256, 300, dtype=np.uint8).tobytes(),
        cb.SYNC + rng.integers(0, 256, 40, dtype=np.uint8).tobytes(),
        bytes([0xA5, 0x5A, cb.SET, 0, 0, 0xF0]) + bytes(20),                        # length > 96
        bytes([0xA5, 0x5A, cb.SET, 0, 0, 52]) + bytes(10),                          # false sync, swallows
        cb.encode_frame(cb.SET, newer, other)[:25],                                  # truncated
        bytes(crc_broken), bytes(flipped),
        cb.encode_frame(cb.SET, last_seq, other),                                    # duplicate seq
        cb.encode_frame(cb.SET, (last_seq - 1) & 0xFFFF, other),                    # stale
        cb.encode_frame(cb.SET, (last_seq + 0x8000) & 0xFFFF, other),               # half a window away
        cb.encode_frame(cb.SET, newer, cb.set_payload((2_500_000,) * 6, (0,) * 6, 0)),   # over the rating
        cb.encode_frame(cb.SET, newer, other[:-1]),                                  # wrong length
        cb.encode_frame(0x7E, newer),                                                # unknown type
        cb.encode_frame(cb.CONFIG, last_seq, cb.config_payload(DEADLINE_US)),      # same deadline
        cb.encode_frame(cb.INFO, 1), cb.encode_frame(cb.PING, 2), cb.encode_frame(cb.PING, 3),
    ]
    order = rng.permutation(len(parts))
    data = b"".join(parts[i] for i in order)
    i = 0
    while i < len(data):                      # in uneven chunks
        n = int(rng.integers(1, 64))
        link.send(data[i:i + n])
        i += n
    return data


def test_deadline_zeroes_through_a_flood_after_the_last_valid_set(board):
    """After the last valid SET the host keeps sending everything except another valid SET, at every frame;
    the clock crosses the uint32 wrap on the way."""
    t_set = 2**32 - 50_000
    board.set_clock_us(t_set)
    link = Link(board.pty)
    rng = np.random.default_rng(12345)
    try:
        status(link.request(cb.CONFIG, 500, cb.config_payload(DEADLINE_US)))
        st = status(link.set(501))
        assert st.dc_ua == DC and st.armed
        before = board.outputs().counters

        def between():
            _flood(link, rng, 501)
            link.sync()

        run_to_deadline(board, t_set, between=between)
        after = board.outputs().counters
        for name in ("crc_errors", "malformed", "rejected", "frames_ok"):
            assert after[name] > before[name], name
    finally:
        link.close()


# --- the safety rules one by one ----------------------------------------------------------------
def test_over_rating_set_is_refused_and_changes_nothing(board):
    link = Link(board.pty)
    try:
        assert board.outputs().output_writes == 1          # power-up: the output stage set to zero
        status(link.request(cb.CONFIG, 10, cb.config_payload(DEADLINE_US)))
        status(link.set(11))
        board.set_clock_us(50_000)
        refused = [
            ((0, 0, 0, 0, 1_500_000, 0), (0, 0, 0, 0, 600_000, 0), 0, cb.R_OVER_RATING, 4),   # 2.1 A > 2 A
            ((-2**31, 0, 0, 0, 0, 0), (0,) * 6, 0, cb.R_OVER_RATING, 0),                    # no overflow
            ((2**31 - 1, 0, 0, 0, 0, 0), (2**31 - 1, 0, 0, 0, 0, 0), 0, cb.R_OVER_RATING, 0),
            ((0, 0, 0, 3_000_001, 0, 0), (0,) * 6, 0, cb.R_OVER_RATING, 3),
            ((0,) * 6, (0,) * 6, 1_000_001, cb.R_FREQ_RANGE, 0),
        ]
        for dc, ac, f, reason, detail in refused:
            n = nak(link.set(12, dc, ac, f))
            assert (n.reason, n.detail, n.rejected_type) == (reason, detail, cb.SET)
            out = board.outputs()
            assert out.armed and out.output_writes == 2
            assert_outputs(out)
        assert board.outputs().counters["rejected"] == len(refused)
        # at the rating exactly is fine; a refused seq was not consumed
        st = status(link.set(12, (3_000_000, 0, 0, 0, 1_000_000, 0), (0, 0, 0, 0, -1_000_000, 0), 1_000_000))
        assert st.dc_ua[0] == 3_000_000 and st.freq_mhz == 1_000_000
    finally:
        link.close()


def test_refused_sets_do_not_restart_the_deadline(board):
    link = Link(board.pty)
    try:
        status(link.set(1))

        def refused():
            nak(link.set(1))                                                  # duplicate
            nak(link.set(2, (5_000_000,) + DC[1:]))                           # over the rating

        run_to_deadline(board, 0, between=refused)
    finally:
        link.close()


def test_config_deadline_is_bounded_by_the_compiled_maximum(board):
    link = Link(board.pty)
    try:
        for d in (500_001, 0, 2**32 - 1):
            n = nak(link.request(cb.CONFIG, 1, cb.config_payload(d)))
            assert n.reason == cb.R_DEADLINE_RANGE and n.rejected_type == cb.CONFIG
        info = cb.decode_info(link.request(cb.INFO, 2))
        assert (info.deadline_us, info.deadline_max_us) == (DEADLINE_US, 500_000)
        assert status(link.request(cb.CONFIG, 3, cb.config_payload(500_000))).deadline_us == 500_000
        status(link.set(4))
        run_to_deadline(board, 0, 500_000)
    finally:
        link.close()


def test_compiled_maximum_is_a_build_option(tmp_path):
    exe = build_host(tmp_path, defines(deadline_max=0.2, ratings=[1, 1, 1, 1, 0.5, 0.5]))
    with HostBoard(exe=str(exe)) as b:
        link = Link(b.pty)
        try:
            assert nak(link.request(cb.CONFIG, 1, cb.config_payload(200_001))).reason == cb.R_DEADLINE_RANGE
            assert status(link.request(cb.CONFIG, 2, cb.config_payload(200_000))).deadline_us == 200_000
            info = cb.decode_info(link.request(cb.INFO, 3))
            assert info.ratings_ua == (1_000_000,) * 4 + (500_000,) * 2
            n = nak(link.set(4, (0, 0, 0, 0, 500_001, 0), (0,) * 6))
            assert (n.reason, n.detail) == (cb.R_OVER_RATING, 4)
        finally:
            link.close()


def test_a_shorter_deadline_applies_at_once(board):
    link = Link(board.pty)
    try:
        status(link.set(1))
        board.set_clock_us(60_000)
        st = status(link.request(cb.CONFIG, 2, cb.config_payload(50_000)))
        assert st.tripped and st.is_zero()
        assert board.outputs().counters["deadline_trips"] == 1
    finally:
        link.close()


def test_sequence_numbers_must_increase_across_the_wrap(board):
    link = Link(board.pty)
    try:
        status(link.set(40_000))                         # the first SET after power-up: any seq
        status(link.request(cb.CONFIG, 65_533, cb.config_payload(DEADLINE_US)))   # a new window
        for k, seq in enumerate((65_534, 65_535, 0, 1)):
            st = status(link.set(seq, (k + 1,) + DC[1:]))
            assert st.last_seq == seq and st.dc_ua[0] == k + 1
        for seq in (1, 0, 65_535, 65_534, 0x8001):       # duplicate, older across the wrap, half a window
            assert nak(link.set(seq, (99,) + DC[1:])).reason == cb.R_STALE_SEQ
        assert board.outputs().dc[0] == pytest.approx(4e-6)
        assert status(link.set(2, (5,) + DC[1:])).dc_ua[0] == 5
    finally:
        link.close()


def test_zero_applies_at_once_whatever_its_seq(board):
    link = Link(board.pty)
    try:
        status(link.set(50))
        writes = board.outputs().output_writes
        status(link.set(51))                             # the same outputs again: the output stage not called
        assert board.outputs().output_writes == writes
        st = status(link.request(cb.ZERO, 3))            # an old seq
        assert st.is_zero() and not st.armed and not st.tripped
        out = board.set_clock_us(10 * DEADLINE_US)
        assert out.is_zero() and not out.tripped and out.counters["deadline_trips"] == 0
        assert out.output_writes == writes + 1
        status(link.set(52))                             # the window was not moved by ZERO
        status(link.set(53, (0,) * 6, (0,) * 6, 5_000))  # a zero SET disarms: nothing to time out
        out = board.set_clock_us(20 * DEADLINE_US)
        assert out.is_zero() and not out.tripped and not out.armed
    finally:
        link.close()


def test_a_frame_behind_a_false_sync_is_found_by_rescanning(board):
    """A false header whose CRC then fails is dropped by one byte only: the real frames it swallowed are
    rescanned and answered, with no clock step and no retry."""
    link = Link(board.pty)
    try:
        ping, setf = cb.encode_frame(cb.PING, 5), cb.encode_frame(cb.SET, 6, cb.set_payload(DC, AC, 20_000))
        link.send(bytes([0xA5, 0x5A, cb.PING, 0, 0, 60]) + ping + setf)
        assert status(link.reply(5)).seq == 5
        assert status(link.reply(6)).dc_ua == DC
        assert board.outputs().counters["crc_errors"] == 1
    finally:
        link.close()


def test_a_false_sync_is_dropped_after_a_silence(board):
    """A partial frame (noise that looks like a header) followed by silence is dropped at the next step more
    than 20 ms later, and a real frame it had swallowed is then found."""
    link = Link(board.pty)
    try:
        link.send(bytes([0xA5, 0x5A, cb.SET, 0, 0, 90]) + cb.encode_frame(cb.PING, 77))
        assert link.reply(77, timeout=0.2) is None           # swallowed, waiting for 90 bytes
        board.set_clock_us(20_000)                            # not yet a gap
        assert link.reply(77, timeout=0.2) is None
        board.set_clock_us(20_001)
        assert status(link.reply(77)).seq == 77
        link.send(cb.encode_frame(cb.SET, 9, cb.set_payload(DC, AC, 1))[:30])   # half a SET, then silence
        board.set_clock_us(50_000)
        status(link.set(9))                                   # the complete SET is accepted
        c = board.outputs().counters
        assert c["malformed"] == 2 and c["crc_errors"] == 0
    finally:
        link.close()


def test_monotonic_clock_trips_by_itself(exe):
    """--clock monotonic: the deadline runs on the host's clock with no traffic at all (5 s hang guard)."""
    from magctl.rig.devices.base import CoilSetpoint
    from magctl.rig.devices.serial_board import SerialCoilBoard

    with HostBoard("monotonic", exe=exe) as b:
        drv = SerialCoilBoard(b.pty, deadline=0.05)
        drv.open()
        try:
            drv.write(CoilSetpoint(np.full(6, 0.5), np.zeros(6), 0.0))
            end = time.monotonic() + 5.0
            while not b.outputs().tripped:
                assert time.monotonic() < end, "the monotonic board never tripped"
                time.sleep(0.01)
            out = b.outputs()
            assert out.is_zero() and out.counters["deadline_trips"] == 1
            assert drv.readback().tripped
        finally:
            drv.close()
