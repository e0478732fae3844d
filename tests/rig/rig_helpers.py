"""Helpers of the rig tests: a real ``magctl rig serve-sim`` subprocess on a free loopback port."""

from __future__ import annotations

import json
import os
import selectors
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class ServerProcess:
    """A ``serve-sim`` subprocess; ``address`` is its endpoint."""

    def __init__(self, *extra: str, env: dict | None = None, ready_timeout: float = 30.0):
        self.address = f"tcp://127.0.0.1:{free_port()}"
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "magctl", "rig", "serve-sim", "--bind", self.address, *extra],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT,
            env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})},
        )
        sel = selectors.DefaultSelector()
        sel.register(self.proc.stdout, selectors.EVENT_READ)
        deadline = time.monotonic() + ready_timeout      # a physics plant solves its oil's flow before "ready"
        while time.monotonic() < deadline:
            if sel.select(timeout=0.2):
                line = self.proc.stdout.readline()
                if line and json.loads(line).get("ready"):
                    return
            if self.proc.poll() is not None:
                break
        err = self.proc.stderr.read().decode() if self.proc.poll() is not None else ""
        self.kill()
        raise RuntimeError(f"serve-sim did not start: {err}")

    def kill(self, sig=signal.SIGKILL) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            self.proc.wait(timeout=10)


def magctl_cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "magctl", *args]
