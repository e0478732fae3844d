"""The coil board's firmware on this computer: find its sources, build the host program, run it behind a pty.

The firmware (``firmware/magcoil/``: ``magcoil.c``, ``magcoil.h``) is portable C99; ``host/magcoil_host.c`` runs
it on a POSIX host behind a pseudo-terminal, which :class:`~magctl.rig.devices.serial_board.SerialCoilBoard` opens
like the board's USB serial port. The tests and a lab server's simulated world use it as the coil hardware:

    with HostBoard(clock="external") as board:          # started; the board's clock moves only when told
        drv = SerialCoilBoard(board.pty)
        ...
        board.advance(0.05)                              # 50 ms pass on the board
        board.outputs().dc                               # what the amplifiers are set to, A

Ratings, the maximum and the power-up deadline are compile-time options of the firmware, as on a real board:
pass them to :class:`HostBoard` (``ratings``, ``deadline_max``, ``deadline``, ``freq_max``, SI units) or as
:func:`defines` to :func:`build_host`; each set of options is its own cached build.
"""

from __future__ import annotations

import hashlib
import json
import os
import select
import shutil
import subprocess
import tempfile
import threading
import time
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np

from magctl.rig.devices.base import CoilSetpoint, DeviceError
from magctl.rig.devices.coilboard import DEFAULT_DEADLINE_MAX_US

HOST_NAME = "magcoil-host"
SOURCES = ("magcoil.h", "magcoil.c", "host/magcoil_host.c")
CFLAGS = ("-std=c99", "-O2", "-Wall", "-Wextra", "-pedantic")
STRICT_CFLAGS = ("-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-Wconversion")
"""The warning set the firmware is kept clean under (tests build with it; :func:`build_host` does not use
-Werror so that a newer compiler's new warning does not stop a lab from running)."""


def firmware_dir() -> Path:
    """The firmware sources: ``firmware/magcoil`` in a source checkout, else ``magctl/_data/firmware/magcoil`` in
    an installed wheel (the rule of :func:`magctl.config.data_dir`)."""
    root = Path(__file__).resolve().parents[3]
    if (root / "pyproject.toml").is_file() and (root / "firmware" / "magcoil").is_dir():
        return root / "firmware" / "magcoil"
    return Path(str(resources.files("magctl") / "_data" / "firmware" / "magcoil"))


def compiler() -> str:
    """The C compiler: ``$CC``, else ``cc``, else ``gcc`` on PATH; a :class:`DeviceError` naming what to install
    when there is none."""
    for name in (os.environ.get("CC"), "cc", "gcc"):
        if name and shutil.which(name):
            return shutil.which(name)
    raise DeviceError(HOST_NAME, "no C compiler (cc or gcc) on PATH to build the simulated coil board; "
                                 "install one, e.g. `apt-get install gcc`")


def defines(ratings=None, deadline_max: float | None = None, deadline: float | None = None,
            freq_max: float | None = None) -> list[str]:
    """The ``-D`` options of the firmware's compile-time limits (magcoil.h) from SI values: ``ratings`` (6 peak
    currents, A), ``deadline_max`` (the longest deadline CONFIG may set, s; default 0.5), ``deadline`` (the
    power-up deadline, s; default 0.1), ``freq_max`` (Hz; default 1000). None keeps the firmware's default."""
    out = []
    if ratings is not None:
        ua = [int(round(float(a) * 1e6)) for a in np.asarray(ratings, dtype=float).reshape(-1)]
        if len(ua) != 6 or min(ua) <= 0 or max(ua) >= 2**31:
            raise ValueError("ratings must be 6 currents in (0, 2147] A")
        out.append("-DMAGCOIL_RATINGS_UA={" + ",".join(f"{v}L" for v in ua) + "}")
    dmax = DEFAULT_DEADLINE_MAX_US if deadline_max is None else int(round(deadline_max * 1e6))
    if not 0 < dmax < 2**32:
        raise ValueError("deadline_max must be in (0, 4294] s")
    if deadline_max is not None:
        out.append(f"-DMAGCOIL_DEADLINE_MAX_US={dmax}UL")
    if deadline is not None:
        d = int(round(deadline * 1e6))
        if not 0 < d <= dmax:
            raise ValueError(f"deadline {deadline:g} s must be in (0, {dmax * 1e-6:g}] s (the deadline maximum)")
        out.append(f"-DMAGCOIL_DEADLINE_DEFAULT_US={d}UL")
    if freq_max is not None:
        out.append(f"-DMAGCOIL_FREQ_MAX_MHZ={int(round(freq_max * 1e3))}UL")
    return out


def cache_dir() -> Path:
    """Where builds are kept: ``$XDG_CACHE_HOME/magctl/firmware`` (default ``~/.cache/magctl/firmware``)."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "magctl" / "firmware"


def build_host(out_dir: str | os.PathLike | None = None, extra_flags: list[str] | tuple[str, ...] = ()) -> Path:
    """Compile the host program (``magcoil_host.c`` + ``magcoil.c``) and return its path.

    The build is cached under ``out_dir`` (default :func:`cache_dir`) in a folder named by a hash of the sources,
    the compiler and the flags: an unchanged firmware is not rebuilt, a changed one is. The binary is written to
    a temporary name and renamed, so concurrent builds never see a half-written file. A missing compiler or a
    failed build raises :class:`DeviceError` (one line, with the compiler's first error).
    """
    cc = compiler()
    src = firmware_dir()
    flags = [*CFLAGS, *extra_flags]
    h = hashlib.sha256()
    for rel in SOURCES:
        try:
            h.update(rel.encode() + b"\0" + (src / rel).read_bytes() + b"\0")
        except OSError as err:
            raise DeviceError(HOST_NAME, f"firmware source missing: {src / rel} ({err.strerror})") from None
    h.update("\0".join([cc, *flags]).encode())
    folder = Path(out_dir) if out_dir is not None else cache_dir()
    exe = folder / h.hexdigest()[:16] / HOST_NAME
    if exe.is_file() and os.access(exe, os.X_OK):
        return exe
    exe.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=HOST_NAME + ".", dir=exe.parent)
    os.close(fd)
    cmd = [cc, *flags, "-o", tmp, str(src / "host" / "magcoil_host.c"), str(src / "magcoil.c")]
    try:
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
        if res.returncode != 0:
            first = next((ln for ln in res.stderr.splitlines() if "error" in ln), res.stderr.strip()[:300])
            raise DeviceError(HOST_NAME, f"building the host firmware failed: {first}")
        os.chmod(tmp, 0o755)
        os.replace(tmp, exe)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return exe


@dataclass(frozen=True)
class BoardOutputs:
    """The host board's outputs as its control channel reports them (``q``)."""

    t_us: int
    dc: np.ndarray
    ac: np.ndarray
    freq: float
    tripped: bool
    armed: bool
    seq: int
    deadline_us: int
    output_writes: int
    counters: dict = field(default_factory=dict)

    @property
    def setpoint(self) -> CoilSetpoint:
        return CoilSetpoint(self.dc, self.ac, self.freq)

    def is_zero(self) -> bool:
        return not (np.any(self.dc) or np.any(self.ac))


class HostBoard:
    """The firmware running as a host process behind a pseudo-terminal (the simulated coil board).

    The constructor builds the program (cached) and starts it, like :class:`subprocess.Popen`; :attr:`pty` is then
    the serial port to open and :attr:`pid` the process. Use it as a context manager (or call :meth:`stop`).

    ``clock="external"``: the board's clock stands still until :meth:`set_clock` / :meth:`advance` (deterministic
    tests; the program processes every byte waiting on the pty before it answers a control command, at the clock
    it had). ``clock="monotonic"``: the board runs on CLOCK_MONOTONIC like the real one. The firmware's limits are
    compile-time options, given here in SI units (see :func:`defines`): ``ratings`` A, ``deadline`` (power-up) and
    ``deadline_max`` s, ``freq_max`` Hz. ``exe`` runs an already built program instead (its own limits).
    """

    def __init__(self, clock: str = "external", *, ratings=None, deadline: float | None = None,
                 deadline_max: float | None = None, freq_max: float | None = None, exe: str | None = None,
                 timeout: float = 10.0):
        if clock not in ("external", "monotonic"):
            raise ValueError("clock must be 'external' or 'monotonic'")
        self.clock = clock
        self._flags = defines(ratings, deadline_max, deadline, freq_max)
        if exe is not None and self._flags:
            raise ValueError("exe is a program built with its own limits: pass either exe or the limits")
        self._exe = exe
        self.timeout = timeout
        self.proc: subprocess.Popen | None = None
        self.pty: str | None = None
        self.t_us = 0
        self._buf = b""
        self._lock = threading.Lock()
        self.start()

    @property
    def pid(self) -> int | None:
        return self.proc.pid if self.proc is not None else None

    def start(self) -> HostBoard:
        """Build (cached) and start the program and read the pty path it prints first (the constructor does this;
        again after :meth:`stop`, a fresh board at power-up)."""
        if self.proc is not None:
            return self
        self._buf = b""
        self.t_us = 0
        exe = self._exe or str(build_host(extra_flags=self._flags))
        self.proc = subprocess.Popen([exe, "--clock", self.clock], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE)
        try:
            self.pty = json.loads(self._readline())["pty"]
        except Exception:
            self.stop()
            raise
        return self

    def _readline(self) -> str:
        """One line of the program's stdout; a :class:`DeviceError` when none comes within the timeout (hang guard)."""
        fd = self.proc.stdout.fileno()
        end = time.monotonic() + self.timeout
        while b"\n" not in self._buf:
            left = end - time.monotonic()
            if left <= 0 or not select.select([fd], [], [], left)[0]:
                raise DeviceError(HOST_NAME, f"no answer within {self.timeout} s")
            chunk = os.read(fd, 65536)
            if not chunk:
                err = self.proc.stderr.read().decode(errors="replace").strip() if self.proc.poll() is not None else ""
                raise DeviceError(HOST_NAME, f"the program exited{': ' + err if err else ''}")
            self._buf += chunk
        line, self._buf = self._buf.split(b"\n", 1)
        return line.decode()

    def _command(self, text: str) -> BoardOutputs:
        with self._lock:
            if self.proc is None or self.proc.poll() is not None:
                raise DeviceError(HOST_NAME, "not running")
            try:
                self.proc.stdin.write(text.encode() + b"\n")
                self.proc.stdin.flush()
            except OSError as err:
                raise DeviceError(HOST_NAME, f"control channel closed: {err}") from None
            d = json.loads(self._readline())
        if "error" in d:
            raise DeviceError(HOST_NAME, d["error"])
        return BoardOutputs(d["t_us"], np.asarray(d["dc_A"], dtype=float), np.asarray(d["ac_A"], dtype=float),
                            float(d["freq_Hz"]), d["tripped"], d["armed"], d["seq"], d["deadline_us"],
                            d["output_writes"], d["counters"])

    def set_clock_us(self, t_us: int) -> BoardOutputs:
        """Set the board's clock to ``t_us`` µs (external clock; never backwards): the deadline is checked at that
        time; the outputs then. The board sees the clock modulo 2^32, as a microcontroller's ``micros()``."""
        out = self._command(f"t {int(t_us)}")
        self.t_us = out.t_us
        return out

    def set_clock(self, t_s: float) -> BoardOutputs:
        """:meth:`set_clock_us` in seconds."""
        return self.set_clock_us(int(round(t_s * 1e6)))

    def advance(self, dt_s: float) -> BoardOutputs:
        """Let ``dt_s`` seconds pass on the board's clock (the ``wait`` of the contract test)."""
        return self.set_clock_us(self.t_us + int(round(dt_s * 1e6)))

    def outputs(self) -> BoardOutputs:
        """The outputs now (``q``: one line each way; cheap enough to call every frame)."""
        return self._command("q")

    def setpoint(self) -> CoilSetpoint:
        """The outputs now as a :class:`CoilSetpoint` (A, Hz)."""
        return self.outputs().setpoint

    def stop(self) -> None:
        """End the program (EOF on its control channel, SIGKILL if it does not exit within a second)."""
        proc, self.proc = self.proc, None
        if proc is None:
            return
        try:
            proc.stdin.close()
        except OSError:
            pass
        try:
            proc.wait(timeout=1.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        proc.stdout.close()
        proc.stderr.close()

    def __enter__(self) -> HostBoard:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
