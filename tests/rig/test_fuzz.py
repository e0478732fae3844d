"""The protocol fuzzer against a real ``serve-sim`` process: a few thousand hostile messages, no exit,
nothing invalid applied, the coils always zeroed by the watchdog (within its bound in simulated time)."""

from __future__ import annotations

import pytest
from rig_helpers import ServerProcess

from magctl.config import load_model
from magctl.rig.fuzz import fuzz

PARAMS = load_model("rig")
PERIOD = 1.0 / PARAMS.runtime.rate
WATCHDOG = PARAMS.watchdog.timeout


@pytest.mark.parametrize("mode, n", [("lockstep", 4000), ("realtime", 1000)])
def test_fuzzer_finds_no_exit_no_invalid_command_and_a_watchdog_in_bound(mode, n):
    """Lock-step: the watchdog's bound is checked in simulated time (exact). Real time: the wall-clock
    watchdog thread must trip in every silent round, with frozen and half-sent peers connected during the
    silence; how late it trips on a loaded machine is a benchmark's number (bench_rig_fuzz), not a test's."""
    srv = ServerProcess(*(["--lockstep"] if mode == "lockstep" else []), "--plant", "standin")
    try:
        rep = fuzz(srv.address, n, seed=7, lockstep=mode == "lockstep", time_budget=120.0,
                   alive=lambda: srv.proc.poll() is None, watchdog=WATCHDOG, period=PERIOD)
        alive = srv.proc.poll() is None
    finally:
        srv.kill()
    assert alive and rep.server_exits == 0
    assert rep.ok, rep.failures
    assert rep.messages >= n and rep.unanswered == 0 and rep.malformed_replies == 0
    assert rep.invalid_applied == 0 and rep.server_applied == rep.accepted_writes > 0
    # every channel was exercised, every kind of refusal seen
    assert set(rep.by_channel) >= {"mutate", "stranger", "noise", "envelope", "multiframe", "tcp"}
    assert {"bad-json", "bad-request", "bad-version", "bad-envelope", "not-owner", "too-large"} <= set(rep.error_codes)
    assert rep.watchdog_checked >= 10 and rep.watchdog_late == 0
    assert all(WATCHDOG < a for a in rep.watchdog_after_s)
    if mode == "lockstep":
        assert all(a <= WATCHDOG + PERIOD + 1e-9 for a in rep.watchdog_after_s)
