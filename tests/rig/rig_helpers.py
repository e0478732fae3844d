"""Helpers of the rig tests: a real ``magctl rig serve-sim`` subprocess on a free loopback port."""

from __future__ import annotations

import signal
import socket
import sys
from pathlib import Path

from magctl.rig.server import start_server

ROOT = Path(__file__).resolve().parents[2]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class ServerProcess:
    """A ``serve-sim`` subprocess; ``address`` is its endpoint."""

    def __init__(self, *extra: str, env: dict | None = None, ready_timeout: float = 30.0):
        self.address = f"tcp://127.0.0.1:{free_port()}"
        # a physics plant solves its oil's flow before "ready"
        self.proc = start_server([sys.executable, "-m", "magctl", "rig", "serve-sim", "--bind", self.address, *extra],
                                 cwd=ROOT, env=env, timeout=ready_timeout)

    def kill(self, sig=signal.SIGKILL) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            self.proc.wait(timeout=10)


def magctl_cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "magctl", *args]


class FakeClock:
    """Monotonic time that advances only when slept on (and by 1 µs per reading, so spins end): a real-time loop
    on it runs its ticks back to back, on schedule (the tests patch a module's ``time`` with it)."""

    def __init__(self):
        self.t = 1000.0

    def monotonic(self):
        self.t += 1e-6
        return self.t

    perf_counter = monotonic

    def sleep(self, dt):
        self.t += max(0.0, dt)

    def time(self):
        return self.t
