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
    w = RunLogWriter(tmp_path / "b.jsonl", max_bytes=12345)
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


# --- the runtime's cap and its log errors ------------------------------------------------------------------
GOTO = {"target_um": [4000.0, 1800.0]}   # far: no arrival within the runs below


def _params_with_max_mb(tmp_path: Path, mb) -> Path:
    """A copy of models/rig.toml whose [log] max_mb is ``mb``."""
    from magctl.config import models_dir

    text = (models_dir() / "rig.toml").read_text()
    old = "max_mb_1 = { value = 100.0,"
    assert old in text
    path = tmp_path / "rig.toml"
    path.write_text(text.replace(old, f"max_mb_1 = {{ value = {mb},"))
    return path


def test_the_runtime_caps_its_log_at_its_rig_toml_and_reports_every_part(tmp_path):
    def runtime(name, **kw):
        return Runtime(SimRig(n_spheres=0, realtime=False, plant="standin"), "goto", GOTO, log_path=tmp_path / name,
                       realtime=False, max_ticks=40, quiet=True, **kw)

    assert runtime("default.jsonl").log_max_bytes == default_part_bytes()
    params = _params_with_max_mb(tmp_path, 0.235)   # the start document is ≈ 0.22 MB: ≈ 15 events a part
    rt = runtime("run.jsonl", params_path=params)
    assert rt.log_max_bytes == 235_000
    report = rt.run()
    back = read_log(tmp_path / "run.jsonl")
    assert report.exit_status == "stopped" and len(back.events) == report.ticks == 40
    assert len(back.parts) >= 2 and report.log_parts == [str(p) for p in back.parts]
    assert report.stats()["log_parts"] == report.log_parts and report.stats()["log"] == report.log_parts[0]
    assert all(p.stat().st_size <= 235_000 for p in back.parts[:-1])
    # given, the cap wins over the file; 0 is no cap
    report = runtime("one.jsonl", params_path=params, log_max_bytes=0).run()
    assert report.log_parts == [str(tmp_path / "one.jsonl")] and not part_path(tmp_path / "one.jsonl", 1).exists()
    assert Runtime(SimRig(n_spheres=0), "goto", GOTO).log_max_bytes is None   # no log, no cap


@pytest.mark.parametrize("given, mb, words", [(-1, None, "must be a number of bytes >= 0"),
                                              (True, None, "must be a number of bytes >= 0"),
                                              (None, 0, r"rig.toml: log.max_mb_1 = 0.0 must be > 0")])
def test_a_bad_cap_is_refused_before_the_rig_is_touched(tmp_path, given, mb, words):
    params = None if mb is None else _params_with_max_mb(tmp_path, mb)
    rig = SimRig(n_spheres=0, realtime=False, plant="standin")
    with pytest.raises(LogError, match=words):
        Runtime(rig, "goto", GOTO, log_path=tmp_path / "x.jsonl", realtime=False, log_max_bytes=given,
                params_path=params)
    assert rig.state is Lifecycle.UNCONFIGURED and not (tmp_path / "x.jsonl").exists()


def test_a_log_that_cannot_be_created_is_refused_before_the_coils_are_live(tmp_path):
    log = tmp_path / "taken.jsonl"
    log.write_text("an earlier run\n")
    rig = SimRig(n_spheres=0, realtime=False, plant="standin")
    with pytest.raises(LogError, match="never overwritten"):
        Runtime(rig, "goto", GOTO, log_path=log, realtime=False, max_ticks=5, quiet=True).run()
    assert rig.activation == 0 and log.read_text() == "an earlier run\n"
    # an activation that fails leaves no empty log behind
    rig = SimRig(n_spheres=0, realtime=False, plant="standin")

    def refuse():
        raise RigError("activation refused")

    rig.activate = refuse
    with pytest.raises(RigError, match="activation refused"):
        Runtime(rig, "goto", GOTO, log_path=tmp_path / "never.jsonl", realtime=False, max_ticks=5, quiet=True).run()
    assert not (tmp_path / "never.jsonl").exists()


def test_a_log_error_that_is_not_a_write_error_ends_the_run_safely(tmp_path, monkeypatch):
    real_event = RunLogWriter.event

    def event(self, seq, *args, **kw):
        if seq == 3:
            raise LogError(f"{self.current}: refusing to write an invalid event document, outputs.x: bad")
        return real_event(self, seq, *args, **kw)

    monkeypatch.setattr(RunLogWriter, "event", event)
    log = tmp_path / "bad.jsonl"
    rig = SimRig(n_spheres=0, realtime=False, plant="standin")
    report = Runtime(rig, "goto", GOTO, log_path=log, realtime=False, max_ticks=20, quiet=True).run()
    assert report.exit_status == "error" and report.reason.startswith(f"{log}: refusing to write")
    assert report.ticks == 3 and rig.state is Lifecycle.INACTIVE and rig.plant.cmd.is_zero()
    back = read_log(log)   # its stop document says why
    assert len(back.events) == 3 and back.stop["exit_status"] == "error" and str(log) in back.stop["reason"]


def _full_at_stop(monkeypatch):
    """A disk that fills just as the stop document is written."""
    _filling_disk(monkeypatch, 10**9)
    real_stop = RunLogWriter.stop

    def stop(self, *args, **kw):
        self._fh.room = 0
        return real_stop(self, *args, **kw)

    monkeypatch.setattr(RunLogWriter, "stop", stop)


def test_a_stop_document_that_cannot_be_written_ends_the_run_with_a_one_line_reason(tmp_path, monkeypatch, capsys):
    _full_at_stop(monkeypatch)
    log = tmp_path / "nostop.jsonl"
    rig = SimRig(n_spheres=0, realtime=False, plant="standin")
    report = Runtime(rig, "goto", GOTO, log_path=log, realtime=False, max_ticks=10, quiet=True).run()
    assert report.exit_status == "error" and report.ticks == 10 and "\n" not in report.reason
    assert report.reason.startswith("max ticks (10) reached; the log's stop document was not written: "
                                    f"{log}: cannot write the run log (No space left on device)")
    assert rig.state is Lifecycle.INACTIVE and rig.plant.cmd.is_zero()
    back = read_log(log)
    assert back.crashed and len(back.events) == 10
    # through the command line: exit 1, the reason on the exit line, no traceback
    cli_log = tmp_path / "cli.jsonl"
    code = main(["rig", "run", "--rig", "sim", "--fast", "--plant", "standin", "--task", "goto", "--target-um",
                 "4000", "1800", "--max-ticks", "5", "--log", str(cli_log)])
    out, err = capsys.readouterr()
    assert code == 1 and "Traceback" not in err
    assert (f"exit: error — max ticks (5) reached; the log's stop document was not written: {cli_log}: cannot "
            f"write the run log") in out


def test_rig_run_json_lists_the_log_parts(tmp_path, capsys):
    log = tmp_path / "run.jsonl"
    code = main(["rig", "run", "--rig", "sim", "--fast", "--plant", "standin", "--task", "goto", "--target-um",
                 "4000", "1800", "--max-ticks", "40", "--log", str(log), "--log-max-mb", "0.235", "--quiet",
                 "--json"])
    doc = json.loads(capsys.readouterr().out)
    parts = read_log(log).parts
    assert code == 0 and len(parts) >= 2 and doc["log_parts"] == [str(p) for p in parts] and doc["log"] == str(log)


def test_the_experiment_caps_its_logs_too(tmp_path, monkeypatch, capsys):
    from magctl.identify import experiment
    from magctl.identify.experiment import RunSpec, run_experiment

    spec = RunSpec("goto", "goto", {"target_um": [1100.0, 1800.0]})   # 100 µm from the default scene's robot
    (path,) = run_experiment("sim", tmp_path / "x", plant="standin", specs=[spec], log_max_bytes=223_500)
    back = read_log(path)
    assert len(back.parts) >= 2 and back.stop["exit_status"] == "done"
    # magctl rig experiment --log-max-mb reaches it in bytes
    seen = {}

    def fake(*args, **kw):
        seen.update(kw)
        return []

    monkeypatch.setattr(experiment, "run_experiment", fake)
    assert main(["rig", "experiment", "--rig", "sim", "--out", str(tmp_path / "y"), "--log-max-mb", "0.5",
                 "--json"]) == 0
    capsys.readouterr()
    assert seen["log_max_bytes"] == 500_000
