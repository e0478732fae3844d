"""Run logs at their limits: a size cap with parts that each read alone, a full disk that stops the run
safely, and a start document whose parameter file names would crash a replay."""

from __future__ import annotations

import errno
import json
import os
from pathlib import Path

import pytest

from magctl.cli import main
from magctl.rig.interface import Lifecycle, RigError
from magctl.rig.log import (
    LogError,
    LogWriteError,
    RunLogWriter,
    default_part_bytes,
    part_path,
    part_size_limit,
    read_log,
    replay,
)
from magctl.rig.runtime import Runtime
from magctl.rig.sim import SimRig

TICKS = 300  # at most (goto ends when it arrives)


def _docs(path: Path) -> list[dict]:
    return [json.loads(x) for x in path.read_text().splitlines()]


@pytest.fixture(scope="module")
def parted(tmp_path_factory):
    """A goto run logged through ``magctl rig run --log-max-mb 0.3``: parts of ≈ 0.3 MB (the start document
    alone is ≈ 0.2 MB)."""
    log = tmp_path_factory.mktemp("parts") / "run.jsonl"
    code = main(["rig", "run", "--rig", "sim", "--fast", "--plant", "standin", "--task", "goto", "--target-um",
                 "4000", "1800", "--max-ticks", str(TICKS), "--log", str(log), "--log-max-mb", "0.3", "--quiet",
                 "--json"])
    assert code == 0
    return log


def test_a_capped_log_goes_on_in_parts_that_each_read_alone(parted):
    parts = [parted] + sorted(parted.parent.glob("run.jsonl.*"), key=lambda p: int(p.suffix[1:]))
    assert len(parts) >= 3 and parts == [part_path(parted, k) for k in range(len(parts))]
    uid = _docs(parted)[0]["uid"]
    seq = 0
    for k, path in enumerate(parts):
        docs = _docs(path)
        assert docs[0]["doc"] == "start" and docs[0]["uid"] == uid and docs[1]["doc"] == "descriptor"
        assert docs[0].get("part", 0) == k and docs[0].get("first_seq", 0) == seq
        # every part but the last stays under the cap; the stop document goes to the last one, whatever its size
        if k < len(parts) - 1:
            assert path.stat().st_size <= 300_000 and docs[-1]["doc"] == "event"
        alone = read_log(path)  # a part reads alone (and with the parts after it)
        assert alone.events[0]["seq"] == seq and alone.stop is not None
        seq += sum(d["doc"] == "event" for d in docs)
    stop = _docs(parts[-1])[-1]
    assert stop["doc"] == "stop" and seq == stop["n_events"] > 200


def test_log_commands_read_the_whole_set_from_its_first_part(parted, tmp_path, capsys):
    log = read_log(parted)
    n = log.stop["n_events"]
    assert len(log.events) == n and len(log.parts) >= 3
    assert [e["seq"] for e in log.events] == list(range(n))
    assert main(["log", "show", str(parted), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["events"] == n and doc["parts"] == len(log.parts) and not doc["crashed"]
    assert main(["log", "replay", str(parted), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["identical"] and doc["commands_compared"] == 2 * n
    out = tmp_path / "x.parquet"
    assert main(["log", "export", str(parted), "--out", str(out), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["events"] == n
    import pyarrow.parquet as pq

    assert pq.read_table(out).column("seq").to_pylist() == list(range(n))
    # a later part alone: shown, but not replayed (the controller starts at the start of the run)
    assert main(["log", "replay", str(part_path(parted, 1))]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "part 1" in err[0] and "run.jsonl" in err[0]


def test_a_part_of_another_run_is_a_one_line_error(parted, tmp_path, capsys):
    a = tmp_path / "a.jsonl"
    a.write_bytes(parted.read_bytes())
    docs = _docs(part_path(parted, 1))
    docs[0]["uid"] = "f" * 32
    part_path(a, 1).write_text("\n".join(json.dumps(d) for d in docs) + "\n")
    assert main(["log", "show", str(a)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "a.jsonl.1:1: not part 1" in err[0]


def test_the_part_size_defaults_to_models_rig_toml_and_a_stale_part_is_refused(tmp_path):
    from magctl.config import load_model

    params = load_model("rig")
    assert params.log.sources["max_mb"] and default_part_bytes() == int(params.log.max_mb * 1e6)
    w = RunLogWriter(tmp_path / "a.jsonl")
    assert w.max_bytes == default_part_bytes()
    w.close()
    with part_size_limit(12345):
        w = RunLogWriter(tmp_path / "b.jsonl")
    assert w.max_bytes == 12345
    w.close()
    (tmp_path / "c.jsonl.1").write_text("")
    with pytest.raises(LogError, match=r"c.jsonl.1 exists"):
        RunLogWriter(tmp_path / "c.jsonl")
    assert not (tmp_path / "c.jsonl").exists()


# --- a full disk -------------------------------------------------------------------------------------------
class FillingFile:
    """A log file on a disk that fills after ``room`` bytes: writes past it raise ENOSPC."""

    def __init__(self, fh, room: int):
        self.fh, self.room = fh, room

    def write(self, data):
        if len(data) > self.room:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        self.room -= len(data)
        return self.fh.write(data)

    def __getattr__(self, name):
        return getattr(self.fh, name)


def _filling_disk(monkeypatch, room):
    real_open = open

    def fake_open(path, mode="r", *args, **kw):
        return FillingFile(real_open(path, mode, *args, **kw), room)

    monkeypatch.setattr("magctl.rig.log.open", fake_open, raising=False)


def test_a_full_disk_stops_the_run_safely_with_an_error_naming_the_log(tmp_path, monkeypatch):
    _filling_disk(monkeypatch, 260_000)  # the start document and some events fit
    log = tmp_path / "full.jsonl"
    rig = SimRig(n_spheres=0, realtime=False, plant="standin")
    report = Runtime(rig, "goto", {"target_um": [4000.0, 1800.0]}, log_path=log, realtime=False,
                     max_ticks=2000, quiet=True).run()
    assert report.exit_status == "error" and str(log) in report.reason
    assert "No space left on device" in report.reason and 0 < report.ticks < 2000
    assert rig.state is Lifecycle.INACTIVE and rig.plant.cmd.is_zero()  # deactivated: coils off
    back = read_log(log)  # the log ends at its last complete line, without a stop document
    assert back.crashed and len(back.events) == report.ticks and "no stop document" in back.crash_note()


def test_a_full_disk_through_rig_run_is_exit_1_naming_the_log(tmp_path, monkeypatch, capsys):
    _filling_disk(monkeypatch, 250_000)
    log = tmp_path / "full.jsonl"
    code = main(["rig", "run", "--rig", "sim", "--fast", "--plant", "standin", "--task", "goto", "--target-um",
                 "4000", "1800", "--max-ticks", "2000", "--log", str(log)])
    out = capsys.readouterr().out
    assert code == 1 and f"exit: error — {log}: cannot write the run log (No space left on device)" in out


def test_dev_full_raises_a_log_write_error_and_nothing_more_is_written(tmp_path):
    if not Path("/dev/full").exists():
        pytest.skip("no /dev/full")
    w = RunLogWriter(tmp_path / "w.jsonl", max_bytes=0)
    w._fh.close()
    w._fh = open("/dev/full", "wb")  # the kernel's own ENOSPC
    with pytest.raises(LogWriteError, match=r"w.jsonl: cannot write the run log \(No space left on device\)") as e:
        w.start(task="goto", options={}, seed=0, rig={}, limits={"b_static_max_T": 1e-3, "b_osc_max_T": 1e-3,
                                                                   "freq_max_Hz": 1.0})
    assert isinstance(e.value, RigError)  # the runtime stops the run on it as on a rig error
    with pytest.raises(LogWriteError):
        w.descriptor({})
    w.stop("error", "disk full")  # closes, writes nothing, raises nothing
    assert w.closed


# --- NUL in a file name ------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def small_log(tmp_path_factory):
    path = tmp_path_factory.mktemp("nul") / "goto.jsonl"
    Runtime(SimRig(n_spheres=0, realtime=False, plant="standin"), "goto", {"target_um": [600.0, 300.0]},
            log_path=path, realtime=False, max_ticks=20, quiet=True).run()
    return path


def _start_edited(src: Path, dst: Path, change) -> Path:
    lines = src.read_text().splitlines()
    start = json.loads(lines[0])
    change(start)
    dst.write_text("\n".join([json.dumps(start)] + lines[1:]) + "\n")
    return dst


@pytest.mark.parametrize("name, change, words", [
    ("nul-name.jsonl", lambda s: s["models_toml"].__setitem__("a\x00b.toml", "x = 1"), "bad parameter file name"),
    ("nul-rig.jsonl", lambda s: s["models_toml"].__setitem__("rig\x00.toml", "x = 1"), "bad parameter file name"),
    ("slash.jsonl", lambda s: s["models_toml"].__setitem__("../up.toml", "x = 1"), "bad parameter file name"),
    ("long.jsonl", lambda s: s["models_toml"].__setitem__("x" * 300 + ".toml", "x = 1"), "bad parameter file name"),
    ("nul-text.jsonl", lambda s: s["models_toml"].__setitem__("rig.toml", s["models_toml"]["rig.toml"] + "\x00"),
     "models_toml: rig.toml: not valid TOML"),
])
def test_a_nul_or_a_path_in_a_logged_file_name_is_a_one_line_replay_error(small_log, tmp_path, capsys, name,
                                                                          change, words):
    bad = _start_edited(small_log, tmp_path / name, change)
    code = main(["log", "replay", str(bad)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and name in err[0] and words in err[0], err
    assert "Traceback" not in "\n".join(err) and "/tmp/tmp" not in err[0]


def test_a_nul_in_a_logged_path_that_replay_does_not_use_is_harmless(small_log, tmp_path, capsys):
    odd = _start_edited(small_log, tmp_path / "odd.jsonl",
                        lambda s: s.update(params_file="/models\x00/rig.toml", argv=["magctl", "a\x00b"]))
    assert replay(odd).identical
    assert main(["log", "show", str(odd)]) == 0
    capsys.readouterr()
