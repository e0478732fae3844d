"""Run logs: crash safety, replay bit for bit, export, and the ``magctl log`` commands."""

from __future__ import annotations

import json
import signal
import subprocess
import time
from pathlib import Path

import h5py
import numpy as np
import pyarrow.parquet as pq
import pytest
from rig_helpers import ROOT, magctl_cmd

from magctl.cli import main
from magctl.rig.log import LogError, RunLogWriter, columns, export, read_log, replay
from magctl.rig.runtime import Runtime
from magctl.rig.sim import SimRig


@pytest.fixture(scope="module")
def push_log(tmp_path_factory):
    path = tmp_path_factory.mktemp("logs") / "push.jsonl"
    report = Runtime(SimRig(n_spheres=1), "front-push", {}, log_path=path, realtime=False, max_ticks=2400,
                     quiet=True).run()
    assert report.exit_status == "done"
    return path


def test_log_documents_in_order(push_log):
    lines = [json.loads(x) for x in push_log.read_text().splitlines()]
    kinds = [d["doc"] for d in lines]
    assert kinds[0] == "start" and kinds[1] == "descriptor" and kinds[-1] == "stop"
    assert set(kinds[2:-1]) == {"event"}
    assert [d["seq"] for d in lines[2:-1]] == list(range(len(lines) - 3))
    assert lines[-1]["exit_status"] == "done" and lines[-1]["n_events"] == len(lines) - 3
    fields = lines[1]["fields"]
    assert fields["obs.spheres_est_m"] == {"shape": [1, 2], "unit": "m"} and fields["cmd.b_osc_T"]["unit"] == "T"


def test_replay_reproduces_the_commands_bit_for_bit(push_log):
    res = replay(push_log)
    assert res.identical and res.compared == 2 * res.events


def test_replay_detects_a_one_ulp_change(push_log, tmp_path):
    lines = push_log.read_text().splitlines()
    ev = json.loads(lines[20])
    ev["cmd"]["b_osc_T"] = float(np.nextafter(ev["cmd"]["b_osc_T"], 1.0))
    lines[20] = json.dumps(ev)
    bad = tmp_path / "tampered.jsonl"
    bad.write_text("\n".join(lines) + "\n")
    res = replay(bad)
    assert not res.identical and res.mismatches == 1 and res.first_mismatch["seq"] == ev["seq"]


def test_sigkill_mid_run_leaves_a_log_that_reads_back_to_the_last_flushed_frame(tmp_path):
    log = tmp_path / "killed.jsonl"
    # in simulated time: a real-time run on a loaded machine may rightly end at its watchdog before the kill
    proc = subprocess.Popen(magctl_cmd("rig", "run", "--rig", "sim", "--task", "patrol", "--fast", "--duration", "3600",
                                       "--log", str(log), "--quiet"), cwd=ROOT,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 300        # a cold start compiles the controller first
    while time.monotonic() < deadline and (not log.exists() or log.read_text().count('"event"') < 15):
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=10)
    flushed = log.read_text()
    n_lines = flushed.count("\n")
    run = read_log(log)
    assert run.crashed and run.stop is None
    assert len(run.events) >= 15 and len(run.events) == n_lines - 2
    assert [e["seq"] for e in run.events] == list(range(len(run.events)))
    assert replay(log).identical


def test_a_torn_last_line_is_dropped_and_the_rest_reads(push_log, tmp_path):
    text = push_log.read_text()
    lines = text.splitlines(keepends=True)
    torn = tmp_path / "torn.jsonl"
    torn.write_text("".join(lines[:12]) + lines[12][: len(lines[12]) // 2])
    run = read_log(torn)
    assert run.torn_tail and run.crashed and len(run.events) == 10


def test_logs_are_never_overwritten_and_bad_logs_are_named(push_log, tmp_path):
    with pytest.raises(LogError, match="never overwritten"):
        RunLogWriter(push_log)
    junk = tmp_path / "junk.jsonl"
    junk.write_text(push_log.read_text().splitlines()[0] + "\nnot json\n")
    with pytest.raises(LogError, match="junk.jsonl:2"):
        read_log(junk)
    other = tmp_path / "other.jsonl"
    other.write_text('{"hello": 1}\n')
    with pytest.raises(LogError, match="not a magctl run log"):
        read_log(other)


@pytest.mark.parametrize("suffix", [".parquet", ".h5"])
def test_export_keeps_every_value(push_log, tmp_path, suffix):
    out = export(push_log, tmp_path / f"run{suffix}")
    run = read_log(push_log)
    if suffix == ".parquet":
        table = pq.read_table(out)
        got = {k: table.column(k).to_numpy() for k in table.column_names}
        meta = json.loads(table.schema.metadata[b"start"])
    else:
        with h5py.File(out) as f:
            got = {k: f["events"][k][()] for k in f["events"]}
            meta = json.loads(f.attrs["start"])
    assert meta["task"] == "front-push"
    assert len(got["seq"]) == len(run.events)
    np.testing.assert_array_equal(got["sphere0_x_m"], [e["obs"]["spheres_est_m"][0][0] for e in run.events])
    np.testing.assert_array_equal(got["cmd_b_osc_T"], [e["cmd"]["b_osc_T"] for e in run.events])
    assert set(got) == set(columns(run))
    with pytest.raises(LogError, match="unknown export format"):
        export(push_log, tmp_path / "run.csv")


def test_log_commands(push_log, tmp_path, capsys):
    def run(*args):
        code = main(["log", *args])
        cap = capsys.readouterr()
        return code, cap.out, cap.err

    code, out, _ = run("show", str(push_log), "--json")
    doc = json.loads(out)
    assert code == 0 and doc["exit_status"] == "done" and doc["task"] == "front-push"
    code, out, _ = run("replay", str(push_log), "--json")
    assert code == 0 and json.loads(out)["identical"] is True
    code, out, _ = run("export", str(push_log), "--out", str(tmp_path / "x.parquet"), "--json")
    assert code == 0 and (tmp_path / "x.parquet").exists()
    code, _, err = run("show", str(tmp_path / "missing.jsonl"))
    assert code == 2 and "missing.jsonl: no such file" in err


def test_replay_uses_the_parameter_files_the_run_used(tmp_path, monkeypatch):
    models = tmp_path / "models"
    models.mkdir()
    for f in (ROOT / "models").glob("*.toml"):
        (models / f.name).write_text(f.read_text())
    servo = (models / "servo.toml").read_text()
    tuned = servo.index("[tuned]")
    # a different servo gain for this run only
    changed = servo[:tuned] + servo[tuned:].replace("kp_per_s = { value = 3.0,", "kp_per_s = { value = 5.0,", 1)
    assert changed != servo
    (models / "servo.toml").write_text(changed)
    monkeypatch.setenv("MAGCTL_MODELS", str(models))
    log = tmp_path / "run.jsonl"
    Runtime(SimRig(n_spheres=0), "goto", {"target_um": [600.0, 300.0]}, log_path=log, realtime=False,
            max_ticks=60, quiet=True).run()
    monkeypatch.delenv("MAGCTL_MODELS")
    assert replay(log).identical  # the logged files, not today's models/, rebuild the controller
    # with the repository's servo.toml instead, the commands differ: the check can fail
    lines = log.read_text().splitlines()
    start = json.loads(lines[0])
    start["models_toml"]["servo.toml"] = servo
    lines[0] = json.dumps(start)
    swapped = tmp_path / "swapped.jsonl"
    swapped.write_text("\n".join(lines) + "\n")
    assert replay(swapped).mismatches > 0


def _edit(push_log, tmp_path, name, fn) -> Path:
    lines = push_log.read_text().splitlines()
    out = tmp_path / name
    data = fn(lines)
    if isinstance(data, bytes):
        out.write_bytes(data)
    else:
        out.write_text("\n".join(data) + "\n")
    return out


def _with(lines, i, change):
    doc = json.loads(lines[i])
    change(doc)
    return lines[:i] + [json.dumps(doc)] + lines[i + 1:]


@pytest.mark.parametrize("name, fn, words", [
    ("binary.jsonl", lambda ls: "\n".join(ls[:5]).encode() + b"\n\xff\xfe\x00garbage\n", "not UTF-8 text"),
    ("nan.jsonl", lambda ls: ls[:3] + [ls[3].replace('"b_osc_T":0.0', '"b_osc_T":NaN', 1)
                                       .replace('"b_osc_T": 0.0', '"b_osc_T": NaN', 1)
                                       .replace('"t_s":', '"t_s":NaN,"x":', 1)] + ls[4:], "NaN is not a JSON number"),
    ("lost.jsonl", lambda ls: _with(ls, 7, lambda d: d["obs"].__setitem__("lost", "no")),
     ":8: event document, obs.lost: 'no' is not of type 'boolean'"),
    ("cmd.jsonl", lambda ls: _with(ls, 9, lambda d: d["cmd"].__setitem__("b_static_T", [1.0])),
     ":10: event document, cmd.b_static_T"),
    ("seq.jsonl", lambda ls: ls[:5] + ls[6:], "event seq 4 where 3 was expected"),
    ("nostart.jsonl", lambda ls: _with(ls, 0, lambda d: d.pop("task")), ":1: start document, document: 'task' is a "
                                                                         "required property"),
    ("after.jsonl", lambda ls: ls + [ls[5]], "after the stop document"),
    ("kind.jsonl", lambda ls: _with(ls, 4, lambda d: d.__setitem__("doc", "frame")), ":5: frame document, doc"),
    ("list.jsonl", lambda ls: ls[:3] + ["[1, 2]"] + ls[4:], ":4: a document must be a JSON object"),
])
def test_malformed_logs_are_one_line_errors_on_every_command(push_log, tmp_path, capsys, name, fn, words):
    bad = _edit(push_log, tmp_path, name, fn)
    for args in (["show", str(bad)], ["replay", str(bad)], ["export", str(bad), "--out", str(tmp_path / "x.h5")]):
        code = main(["log", *args])
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(err) == 1 and words in err[0] and name in err[0], (args, err)


def test_a_directory_is_not_a_log(tmp_path, capsys):
    assert main(["log", "show", str(tmp_path)]) == 2
    assert "is a folder, not a file" in capsys.readouterr().err


def test_a_crashed_log_says_so_and_up_to_where_it_is_complete(push_log, tmp_path, capsys):
    lines = push_log.read_text().splitlines()
    crashed = tmp_path / "crashed.jsonl"
    crashed.write_text("\n".join(lines[:42]) + "\n" + lines[42][:30])  # 40 events, then a torn line, no stop
    code = main(["log", "replay", str(crashed)])
    cap = capsys.readouterr()
    assert code == 0 and "identical" in cap.out and "no stop document" in cap.out and "seq 39" in cap.out
    assert "no stop document" in cap.err and "complete up to event seq 39" in cap.err and "torn" in cap.err
    code = main(["log", "show", str(crashed), "--json"])
    cap = capsys.readouterr()
    doc = json.loads(cap.out)
    assert code == 0 and doc["crashed"] and doc["complete_to"]["seq"] == 39 and "no stop document" in cap.err
    # a complete log carries no such note
    main(["log", "replay", str(push_log)])
    cap = capsys.readouterr()
    assert "stop document" not in cap.out + cap.err


def test_the_writer_refuses_an_invalid_document(tmp_path):
    w = RunLogWriter(tmp_path / "w.jsonl")
    with pytest.raises(LogError, match="refusing to write an invalid start document"):
        w.start(task="goto", options={}, seed="zero", rig={}, limits={})
    w.close()


def test_log_show_is_in_micrometres_with_status_and_phase_names(push_log, capsys):
    """``log show``: positions in µm, speeds in µm/s, status and phase by name, no SI float noise."""
    from magctl.control.push.front import FrontPushTask
    from magctl.control.status import STATUS_NAMES

    assert main(["log", "show", str(push_log), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    outs = doc["final_outputs"]
    assert outs["status"] in STATUS_NAMES.values()
    assert outs["phase"] in FrontPushTask.PHASES.values()
    assert "target_um" in outs and "target" not in outs
    opts = doc["options"]
    assert "push_speed_m_s" not in opts
    assert all(round(v, 3) == v for v in outs["target_um"])          # rounded to the nanometre
    raw = read_log(push_log)
    assert outs["target_um"] == pytest.approx([x * 1e6 for x in raw.events[-1]["outputs"]["target"]], abs=1e-3)
    assert opts["push_speed_um_s"] == pytest.approx(raw.start["options"]["push_speed_m_s"] * 1e6)
    assert main(["log", "show", str(push_log)]) == 0
    text = capsys.readouterr().out
    assert f"status {outs['status']}" in text and "µm/s" in text and "final robot: [" in text
    assert "e-0" not in text                                           # no SI floats such as 9.99e-06


def test_an_undefined_output_is_logged_as_null_and_a_non_finite_observation_is_refused_by_name(tmp_path):
    """The side push's gap is NaN until its first attempt (a lost first frame keeps it so): the log carries it as
    null, and every reader takes it; a NaN where the log needs a number is a LogError naming the field."""
    from magctl.rig.interface import Observation
    from magctl.rig.runtime import _scalar

    assert _scalar(np.array([np.nan])) is None and _scalar(np.array([[np.nan, 1.5]])) == [None, 1.5]
    assert _scalar(np.array([True])) is True and _scalar(np.array([2.0])) == 2.0
    obs = Observation(t=0.0, frame=0, robot_est=np.array([1e-3, 1e-3]), heading_est=0.0,
                      spheres_est=np.array([[2e-3, 1e-3]]), lost=True)
    w = RunLogWriter(tmp_path / "null.jsonl")
    w.start(task="side-push", options={}, seed=0, rig={}, limits={"b_static_max_T": 3e-3, "b_osc_max_T": 3e-3,
                                                                 "freq_max_Hz": 200.0})
    w.descriptor({"outputs.gap": {"shape": [], "unit": "m"}})
    timing = dict.fromkeys(("scheduled_s", "start_s", "jitter_s", "read_s", "compute_s", "write_s"), 0.0)
    w.event(0, obs, None, None, {"gap": None, "target": [None, None]}, {**timing, "skipped": 0}, 1)
    bad = Observation(t=0.0, frame=1, robot_est=np.array([1e-3, np.nan]), heading_est=0.0,
                      spheres_est=np.array([[2e-3, 1e-3]]), lost=False)
    with pytest.raises(LogError, match=r"refusing to write event seq 1: obs.robot_est_m\[1\] is not a finite"):
        w.event(1, bad, None, None, {"gap": 1e-4}, {**timing, "skipped": 0}, 1)
    w.stop("stopped", "test")
    log = read_log(tmp_path / "null.jsonl")
    assert [e["outputs"]["gap"] for e in log.events] == [None]
    assert np.isnan(columns(log)["out_gap"][0])
    assert log.summary()["final_outputs"]["gap_um"] is None
