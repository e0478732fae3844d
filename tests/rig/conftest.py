"""Fixtures: a real ``magctl rig serve-sim`` subprocess on a free loopback port."""

from __future__ import annotations

import pytest
from rig_helpers import ServerProcess


@pytest.fixture(scope="module")
def server():
    """A lock-step server: one plant frame per read, the watchdog in simulated time (deterministic)."""
    srv = ServerProcess("--lockstep")
    yield srv
    srv.kill()


@pytest.fixture
def start_server():
    started = []

    def start(*extra, env=None):
        srv = ServerProcess(*extra, env=env)
        started.append(srv)
        return srv

    yield start
    for srv in started:
        srv.kill()
