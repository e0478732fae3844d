"""Replaying a run that planned off the frame: each plan merged at the tick its log says (``event_applied``), however
late, so a real-time run — whose plans came back two or more ticks after their request — replays bit for bit; a
log whose merge ticks were edited replays to its first differing tick, not to a crash (docs/rig.md).

The late merges are scripted (the lock-step runtime merges the n-th plan ``DELAYS[n]`` ticks after its request), so
the run is a function of its seed; one run on a fake real-time clock merges each plan whenever the worker is done.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from rig_helpers import FakeClock

from magctl.cli import main
from magctl.rig.log import read_log, replay
from magctl.rig.runtime import Runtime
from magctl.rig.sim import SimRig

OPTIONS = {"n_spheres": 3}   # the planned assembly: a plan at the start and after each pass
DELAYS = (4, 9, 2)
"""Ticks from each plan's request to its merge, in turn (a real-time rig merges a 20-50 ms plan 2 ticks after the
request, later on a loaded machine)."""


class LateMerges(Runtime):
    """The lock-step runtime merging its n-th plan ``DELAYS[n % 3]`` ticks after the tick that requested it (waiting
    for the worker then): a real-time run whose plans came back late, on a script."""

    def _apply_events(self, ctrl, pending, tick):
        applied = -1
        for p in list(pending):
            n = next(i for i, q in enumerate(self._events) if q is p)
            if tick - p.requested < DELAYS[n % len(DELAYS)]:
                continue
            result, _seconds = p.future.result()
            ctrl.apply(p.request, result)
            p.applied = tick
            pending.remove(p)
            applied = p.requested
        return applied


def merges(log) -> list[tuple[int, int | None]]:
    """(requesting seq, merging seq) of every plan, from the events' own fields."""
    requested = [e["seq"] for e in log.events if e["outputs"]["event_requested"]]
    applied = {e["outputs"]["event_applied"]: e["seq"] for e in log.events if e["outputs"]["event_applied"] >= 0}
    return [(r, applied.get(r)) for r in requested]


@pytest.fixture(scope="module")
def late_log(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("late") / "late.jsonl"
    report = LateMerges(SimRig(n_spheres=3, seed=0), "assemble", OPTIONS, realtime=False, max_ticks=1100,
                        log_path=path, quiet=True).run()
    assert report.exit_status == "stopped", report.reason
    return path


def test_a_run_whose_plans_were_merged_late_replays_bit_for_bit(late_log, capsys):
    log = read_log(late_log)
    made = [(r, a) for r, a in merges(log) if a is not None]
    assert len(made) >= 3
    assert [a - r for r, a in made] == [DELAYS[n % len(DELAYS)] for n in range(len(made))]
    for r, a in made:   # the ticks in between held the robot, and said so
        held = log.events[r + 1:a]
        assert held and all(e["outputs"]["event_pending"] and e["cmd"]["b_osc_T"] == 0.0 for e in held)
    res = replay(late_log)
    assert res.identical and res.compared == 2 * len(log.events) and res.merged == len(made)
    assert main(["log", "replay", str(late_log), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["identical"] and doc["mismatches"] == 0 and doc["commands_compared"] == 2 * len(log.events)


def test_the_on_frame_controller_would_not_reproduce_it(late_log, monkeypatch):
    """Without the merge ticks (the replay of before), the first plan is used from the tick after its request,
    where the run still held the robot: the replay differs there."""
    import magctl.rig.log as log_mod

    monkeypatch.setattr(log_mod, "deferred_events", lambda log: False)
    res = replay(late_log)
    assert not res.identical and res.first_mismatch["seq"] == 1 and res.merged == 0


def test_a_run_planning_inside_the_tick_replays_as_before(tmp_path):
    path = tmp_path / "on.jsonl"
    Runtime(SimRig(n_spheres=3, seed=0), "assemble", OPTIONS, realtime=False, max_ticks=40, log_path=path,
            quiet=True, off_frame=False).run()
    log = read_log(path)
    assert "event_applied" not in log.events[0]["outputs"]
    res = replay(path)
    assert res.identical and res.merged == 0


def _tampered(src: Path, dst: Path, edits: dict[int, object]) -> Path:
    """``src`` with ``outputs.event_applied`` of event seq k set to ``edits[k]``."""
    lines = src.read_text().splitlines()
    for seq, value in edits.items():
        doc = json.loads(lines[2 + seq])
        assert doc["doc"] == "event" and doc["seq"] == seq
        doc["outputs"]["event_applied"] = value
        lines[2 + seq] = json.dumps(doc)
    dst.write_text("\n".join(lines) + "\n")
    return dst


@pytest.mark.parametrize("case", ["later", "earlier", "before-the-request", "half-a-tick", "true", "a-list",
                                  "another-plan"])
def test_a_tampered_merge_tick_is_the_first_differing_tick(late_log, tmp_path, case):
    (r0, a0), (r1, _a1) = merges(read_log(late_log))[:2]
    edits, first, field, only = {
        "later": ({a0: -1, a0 + 1: r0}, a0, "outputs.event_pending", False),        # held one tick too long
        "earlier": ({a0: -1, a0 - 1: r0}, a0 - 1, "outputs.event_pending", False),  # merged a tick too soon
        "before-the-request": ({r0: r0}, r0, "outputs.event_applied", True),        # that plan is not asked for yet
        "half-a-tick": ({a0: 2.5}, a0, "outputs.event_applied", False),
        "true": ({a0: True}, a0, "outputs.event_applied", False),
        "a-list": ({a0: [r0]}, a0, "outputs.event_applied", False),
        "another-plan": ({a0: r1}, a0, "outputs.event_applied", True),              # merges r0 anyway
    }[case]
    res = replay(_tampered(late_log, tmp_path / f"{case}.jsonl", edits))
    assert not res.identical and res.first_mismatch["seq"] == first and res.first_mismatch["field"] == field
    assert res.compared == replay(late_log).compared          # the replay went on to the end
    if only:   # the plan was merged where the run merged it: that field alone differs
        assert res.mismatches == 1
    else:      # the plan was merged elsewhere, or never: the commands differ too
        assert res.mismatches > 1


def test_a_tampered_log_through_the_command_line_is_exit_1_naming_the_tick(late_log, tmp_path, capsys):
    (r0, a0) = merges(read_log(late_log))[0]
    bad = _tampered(late_log, tmp_path / "bad.jsonl", {a0: -1, a0 + 2: r0})
    assert main(["log", "replay", str(bad), "--json"]) == 1
    captured = capsys.readouterr()
    doc = json.loads(captured.out)
    assert not doc["identical"] and doc["first_mismatch"]["seq"] == a0 and "Traceback" not in captured.err



def test_a_real_time_run_replays_whenever_its_plans_came_back(tmp_path, monkeypatch):
    """Real time on a fake clock: the ticks run back to back while the worker plans in real time, so each plan is
    merged at whatever later tick finds it ready (the log says which); the replay reproduces the run all the same."""
    import magctl.rig.runtime as runtime_mod
    import magctl.rig.station as station_mod

    clock = FakeClock()
    monkeypatch.setattr(runtime_mod, "time", clock)
    monkeypatch.setattr(station_mod, "time", clock)
    path = tmp_path / "realtime.jsonl"
    report = Runtime(SimRig(n_spheres=3, realtime=True, seed=0), "assemble", OPTIONS, realtime=True, max_ticks=500,
                     log_path=path, quiet=True).run()
    assert report.exit_status == "stopped", report.reason
    made = [(r, a) for r, a in merges(read_log(path)) if a is not None]
    assert made and all(a > r for r, a in made)
    res = replay(path)
    assert res.identical and res.merged == len(made)
