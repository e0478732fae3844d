"""The coil board's protocol: the C firmware builds clean, the documented example's CRC is right, the Python
encoder and the firmware understand each other, the decoder resynchronises, the build helper caches."""

from __future__ import annotations

import binascii
import os
import re
import shutil
import subprocess
import tty
from pathlib import Path

import numpy as np
import pytest

from magctl.rig.devices import coilboard as cb
from magctl.rig.devices.base import DeviceError
from magctl.rig.devices.firmware import STRICT_CFLAGS, HostBoard, build_host, compiler, firmware_dir

ROOT = Path(__file__).resolve().parents[3]
FW = firmware_dir()
CC = compiler()


@pytest.fixture(scope="module")
def exe(tmp_path_factory):
    return str(build_host(tmp_path_factory.mktemp("fw")))


def _cc(*args: str, cwd=None) -> subprocess.CompletedProcess:
    return subprocess.run([CC, *args], capture_output=True, text=True, cwd=cwd, timeout=120)


# --- the C builds ---------------------------------------------------------------------------------
def test_firmware_dir_is_the_checkout():
    assert FW == ROOT / "firmware" / "magcoil"
    for rel in ("magcoil.h", "magcoil.c", "host/magcoil_host.c", "arduino/magcoil.ino"):
        assert (FW / rel).is_file(), rel


def test_firmware_compiles_with_werror(tmp_path):
    """The core and the host program are clean under -Wall -Wextra -Werror -pedantic -Wconversion, also with the
    limits overridden by -D."""
    res = _cc(*STRICT_CFLAGS, "-Wsign-conversion", "-c", str(FW / "magcoil.c"), "-o", str(tmp_path / "a.o"))
    assert res.returncode == 0, res.stderr
    res = _cc(*STRICT_CFLAGS, "-DMAGCOIL_RATINGS_UA={1L,2L,3L,4L,5L,6L}", "-DMAGCOIL_DEADLINE_MAX_US=250000UL",
              "-DMAGCOIL_FREQ_MAX_MHZ=200000UL", "-o", str(tmp_path / "host"),
              str(FW / "host" / "magcoil_host.c"), str(FW / "magcoil.c"))
    assert res.returncode == 0, res.stderr


def test_firmware_header_includes_only_freestanding_headers():
    """Portable to boards without a C library: no headers beyond <stdint.h>, <stddef.h>, <string.h>."""
    for name in ("magcoil.h", "magcoil.c"):
        includes = re.findall(r"#include\s+[<\"]([^>\"]+)", (FW / name).read_text())
        assert set(includes) <= {"stdint.h", "stddef.h", "string.h", "magcoil.h"}, (name, includes)
    src = (FW / "magcoil.c").read_text()
    assert not re.search(r"\b(malloc|free|float|double)\b", src)


def test_firmware_compiles_32bit(tmp_path):
    """-m32: hosted when the 32-bit C library is installed, else freestanding (the core needs no libc)."""
    probe = tmp_path / "probe.c"
    probe.write_text("#include <stdint.h>\n#include <stddef.h>\nint f(void);\nint f(void) { return 0; }\n")
    for mode in ([], ["-ffreestanding"]):
        if _cc("-m32", *mode, "-c", str(probe), "-o", str(tmp_path / "p.o")).returncode == 0:
            break
    else:
        pytest.skip("the compiler cannot target -m32 here")
    res = _cc(*STRICT_CFLAGS, "-m32", *mode, "-c", str(FW / "magcoil.c"), "-o", str(tmp_path / "m32.o"))
    assert res.returncode == 0, res.stderr


ARDUINO_STUB = """
/* just enough of Arduino.h to type-check the board file */
#include <stdint.h>
#include <stddef.h>
#include <string.h>
#define HIGH 1
#define LOW 0
#define OUTPUT 1
unsigned long micros(void);
void pinMode(uint8_t pin, uint8_t mode);
void digitalWrite(uint8_t pin, uint8_t val);
void analogWrite(uint8_t pin, int val);
struct SerialStub {
    void begin(unsigned long baud);
    int available(void);
    int read(void);
    int availableForWrite(void);
    size_t write(const uint8_t *buf, size_t n);
};
extern SerialStub Serial;
"""


def test_arduino_board_file_type_checks_against_a_stub(tmp_path):
    """The .ino cannot be built here; with a stub of the Arduino API it at least compiles as C++ without warnings."""
    cxx = next((c for c in ("c++", "g++", "clang++") if shutil.which(c)), None)
    if cxx is None:
        pytest.skip("no C++ compiler")
    (tmp_path / "Arduino.h").write_text(ARDUINO_STUB)
    res = subprocess.run([cxx, "-std=c++11", "-Wall", "-Wextra", "-Werror", "-fsyntax-only", "-include",
                          str(tmp_path / "Arduino.h"), f"-I{FW}", "-x", "c++", str(FW / "arduino" / "magcoil.ino")],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr


def test_waveform_helpers_match_sine(tmp_path):
    """The integer sine of the board file is within 0.01 % of sin, and the phase step is exact."""
    harness = tmp_path / "wave.c"
    harness.write_text(r"""
#include <stdio.h>
#include "magcoil.h"
void magcoil_output(const magcoil_outputs_t *o, void *ctx) { (void)o; (void)ctx; }
int main(void) {
    unsigned long i;
    magcoil_outputs_t o = {{1000000, 0, 0, 0, 0, 0}, {-500000, 0, 0, 0, 0, 0}, 20000};
    for (i = 0; i < 4096; i++) printf("%ld\n", (long)magcoil_sin_q15((uint32_t)(i * 1048576ul + i * 7ul)));
    printf("%lu %lu %lu\n", (unsigned long)magcoil_phase_step(20000u, 12500u),
           (unsigned long)magcoil_phase_step(1000000u, 4294967295u), (unsigned long)magcoil_phase_step(1u, 1u));
    printf("%ld %ld\n", (long)magcoil_current_ua(&o, 0, 0x40000000ul), (long)magcoil_current_ua(&o, 0, 0xC0000000ul));
    return 0;
}
""")
    res = _cc("-std=c99", f"-I{FW}", "-o", str(tmp_path / "wave"), str(harness), str(FW / "magcoil.c"))
    assert res.returncode == 0, res.stderr
    lines = subprocess.run([str(tmp_path / "wave")], capture_output=True, text=True, check=True).stdout.split("\n")
    s = np.array([int(v) for v in lines[:4096]])
    phase = np.array([(i * 1048576 + i * 7) % 2**32 for i in range(4096)]) / 2**32
    assert np.max(np.abs(s / 32767 - np.sin(2 * np.pi * phase))) < 1e-4
    steps = [int(v) for v in lines[4096].split()]
    # 20 Hz for 12.5 ms = 0.25 cycle; 1 kHz for 2^32-1 us: frac(4294967.295) cycles; 1 mHz for 1 us
    assert steps[0] == 2**30
    assert steps[1] == int(0.295 * 2**32)
    assert steps[2] == int(1e-9 * 2**32)
    assert [int(v) for v in lines[4097].split()] == [500000, 1500000]


# --- CRC and frames -------------------------------------------------------------------------------
def _worked_example() -> bytes:
    text = (ROOT / "docs" / "coil-board.md").read_text()
    block = re.search(r"<!-- worked-example -->\s*```\s*\n(.*?)```", text, re.S)
    assert block, "docs/coil-board.md lost its worked example"
    return bytes.fromhex(block.group(1).replace("\n", " "))


def test_worked_example_crc_is_crc_ccitt_false():
    """The documented frame's CRC is what an independent CRC-16/CCITT-FALSE (binascii.crc_hqx) gives, and
    the frame decodes to the values the doc states."""
    frame = _worked_example()
    assert frame[:2] == cb.SYNC and frame[5] == len(frame) - 8
    assert int.from_bytes(frame[-2:], "little") == binascii.crc_hqx(frame[2:-2], 0xFFFF) == 0x8162
    (f,) = cb.StreamDecoder().feed(frame)
    assert (f.type, f.seq) == (cb.SET, 7)
    dc, ac, freq = cb.decode_set(f.payload)
    assert dc == (1_200_000, -1_200_000, 0, 0, 500_000, 0)
    assert ac == (100_000, 100_000, 0, 0, 0, -250_000)
    assert freq == 20_000
    assert cb.encode_frame(cb.SET, 7, cb.set_payload(dc, ac, freq)) == frame


def test_crc_matches_binascii():
    rng = np.random.default_rng(1)
    assert cb.crc16(b"123456789") == 0x29B1
    for n in (0, 1, 5, 52, 96, 300):
        data = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        assert cb.crc16(data) == binascii.crc_hqx(data, 0xFFFF)


def test_payload_round_trips():
    st = cb.Status(9, True, False, 65535, 100000, None, (1, -2, 3, -4, 5, -2**31), (0,) * 6, 1_000_000,
                   dict(zip(cb.COUNTER_NAMES, range(1, 7))))
    assert cb.decode_status(cb.Frame(cb.STATUS, 9, cb.status_payload(st))) == st
    assert len(cb.set_payload([0] * 6, [0] * 6, 0)) == cb.SET_LEN == 52
    assert (cb.STATUS_LEN, cb.INFO_LEN, cb.NAK_LEN) == (88, 44, 3)
    with pytest.raises(cb.ProtocolError):
        cb.decode_status(cb.Frame(cb.STATUS, 1, b"\0" * 10))
    with pytest.raises(cb.ProtocolError):
        cb.encode_frame(cb.SET, 1, b"\0" * 97)


def test_seq_newer_wraps():
    assert cb.seq_newer(1, 0) and cb.seq_newer(0, 65535) and cb.seq_newer(5, 65530)
    assert not cb.seq_newer(7, 7) and not cb.seq_newer(65535, 0) and not cb.seq_newer(0x8000, 0)
    assert cb.seq_newer(0x7FFF, 0)


def test_quantisation_never_exceeds_a_rating():
    dc, ac = cb.amps_to_ua(np.array([1.5000004, 0.4 * 3, -2.0]), np.array([1.4999999, -0.3, 0.0]),
                           [3_000_000, 3_000_000, 2_000_000])
    assert abs(dc[0]) + abs(ac[0]) <= 3_000_000
    assert dc[1:] == [1_200_000, -2_000_000] and ac[1:] == [-300_000, 0]
    assert cb.hz_to_mhz(20.0) == 20_000 and cb.hz_to_mhz(0.0015) == 2


# --- the streaming decoder ------------------------------------------------------------------------
def test_decoder_resynchronises():
    """Noise, a bad CRC, an impossible length and a false sync that swallows a real frame: every real frame is
    still found, whatever the chunking."""
    ping = cb.encode_frame(cb.PING, 1)
    setf = cb.encode_frame(cb.SET, 2, cb.set_payload([1] * 6, [2] * 6, 3))
    bad = bytearray(setf)
    bad[20] ^= 0x10
    false_sync = bytes([0xA5, 0x5A, 0x01, 0x00, 0x00, 40])     # claims 40 payload bytes: swallows what follows
    too_long = bytes([0xA5, 0x5A, 0x02, 0x00, 0x00, 200])
    stream = b"\x00\xa5\xff" + ping + bytes(bad) + too_long + false_sync + setf + b"\x5a\xa5" + ping + b"\x00" * 60
    for chunk in (1, 3, 7, len(stream)):
        dec = cb.StreamDecoder()
        frames = []
        for i in range(0, len(stream), chunk):
            frames += dec.feed(stream[i:i + chunk])
        assert [(f.type, f.seq) for f in frames] == [(cb.PING, 1), (cb.SET, 2), (cb.PING, 1)]
        assert dec.crc_errors >= 2 and dec.malformed >= 1


def test_decoder_expire_releases_a_frame_behind_a_false_sync():
    dec = cb.StreamDecoder()
    ping = cb.encode_frame(cb.PING, 77)
    assert dec.feed(bytes([0xA5, 0x5A, 0x01, 0x00, 0x00, 90]) + ping) == []
    assert dec.pending > 0
    assert [f.seq for f in dec.expire()] == [77]
    assert dec.pending == 0


# --- Python ↔ firmware ----------------------------------------------------------------------------
class _Raw:
    """The board's pty opened raw by the test, one request at a time."""

    def __init__(self, path: str):
        self.fd = os.open(path, os.O_RDWR | os.O_NOCTTY)
        tty.setraw(self.fd)
        self.dec = cb.StreamDecoder()

    def request(self, frame: bytes, seq: int, timeout: float = 5.0) -> cb.Frame:
        import select
        import time

        os.write(self.fd, frame)
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if select.select([self.fd], [], [], 0.05)[0]:
                for f in self.dec.feed(os.read(self.fd, 4096)):
                    if f.seq == seq:
                        return f
        raise AssertionError(f"no reply to seq {seq}")

    def close(self):
        os.close(self.fd)


def test_python_frames_are_accepted_by_the_firmware(exe):
    """SET, CONFIG, INFO, PING, ZERO encoded in Python are applied by the C firmware; its replies decode, and
    agree with the outputs its control channel reports."""
    with HostBoard(exe=exe) as board:
        raw = _Raw(board.pty)
        try:
            st = cb.decode_status(raw.request(cb.encode_frame(cb.CONFIG, 100, cb.config_payload(200_000)), 100))
            assert st.deadline_us == 200_000 and st.last_seq == 100 and st.is_zero()
            info = cb.decode_info(raw.request(cb.encode_frame(cb.INFO, 3), 3))
            assert info.version == cb.VERSION and info.ratings_ua == cb.DEFAULT_RATINGS_UA
            assert (info.freq_max_mhz, info.deadline_max_us, info.deadline_us) == (1_000_000, 500_000, 200_000)
            dc, ac = (1_234_567, -2, 0, 0, -1_999_999, 7), (-1_000_000, 0, 0, 3, 1, -7)
            f = raw.request(cb.encode_frame(cb.SET, 101, cb.set_payload(dc, ac, 123_456)), 101)
            st = cb.decode_status(f)
            assert (f.type, st.seq, st.dc_ua, st.ac_ua, st.freq_mhz) == (cb.STATUS, 101, dc, ac, 123_456)
            assert st.armed and not st.tripped and st.since_set_us == 0
            out = board.outputs()
            np.testing.assert_array_equal(np.rint(out.dc * 1e6), dc)
            np.testing.assert_array_equal(np.rint(out.ac * 1e6), ac)
            assert out.freq == pytest.approx(123.456, abs=1e-9)
            board.advance(0.05)
            st = cb.decode_status(raw.request(cb.encode_frame(cb.PING, 5), 5))
            assert st.since_set_us == 50_000 and st.dc_ua == dc
            nak = cb.decode_nak(raw.request(cb.encode_frame(0x42, 6), 6))
            assert (nak.reason, nak.rejected_type) == (cb.R_UNKNOWN_TYPE, 0x42)
            nak = cb.decode_nak(raw.request(cb.encode_frame(cb.PING, 7, b"\0"), 7))
            assert (nak.reason, nak.detail) == (cb.R_BAD_LENGTH, 1)
            st = cb.decode_status(raw.request(cb.encode_frame(cb.ZERO, 8), 8))
            assert st.is_zero() and not st.armed and st.since_set_us is None
            assert st.counters["frames_ok"] == 5 and st.counters["rejected"] == 2
        finally:
            raw.close()


# --- the build helper -----------------------------------------------------------------------------
def test_build_host_is_cached_by_source_and_flags(tmp_path):
    a = build_host(tmp_path)
    mtime = a.stat().st_mtime_ns
    assert build_host(tmp_path) == a and a.stat().st_mtime_ns == mtime
    b = build_host(tmp_path, ["-DMAGCOIL_DEADLINE_MAX_US=300000UL"])
    assert b != a and b.is_file()
    assert sorted(p.name for p in b.parent.iterdir()) == ["magcoil-host"]   # no temporary left behind


def test_missing_compiler_is_one_line_device_error(tmp_path, monkeypatch):
    monkeypatch.setenv("PATH", str(tmp_path))
    monkeypatch.delenv("CC", raising=False)
    with pytest.raises(DeviceError, match=r"magcoil-host: no C compiler .*install") as err:
        build_host(tmp_path)
    assert "\n" not in str(err.value)


def test_host_control_channel_errors(exe):
    with HostBoard(exe=exe) as board:
        board.set_clock_us(1000)
        with pytest.raises(DeviceError, match="backwards"):
            board.set_clock_us(999)
        assert board.outputs().t_us == 1000
        assert board.setpoint().is_zero()
        pid = board.pid
        board.stop()
        with pytest.raises(DeviceError, match="not running"):
            board.outputs()
        board.start()                                       # a fresh board, at power-up
        assert board.pid != pid and board.outputs().t_us == 0
    with HostBoard("monotonic", exe=exe) as board:
        with pytest.raises(DeviceError, match="external"):
            board.set_clock_us(5)
        assert board.outputs().is_zero()

