"""Every ordinary mistake on the command line: one line on stderr naming the option, a non-zero exit
code, no traceback, and no work done.

Each case runs ``python -m magctl`` in a subprocess, as a user would, so what is checked is what a
terminal shows: the whole of stderr.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _env() -> dict:
    return dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))


def _run(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "magctl", *args], cwd=cwd, env=_env(), capture_output=True,
                          text=True, timeout=120, stdin=subprocess.DEVNULL)


def _assert_one_line(done: subprocess.CompletedProcess, names: str) -> str:
    err = done.stderr
    assert done.returncode != 0, (done.returncode, done.stdout, err)
    assert "Traceback" not in err, err
    lines = err.splitlines()
    assert len(lines) == 1, err
    assert names in lines[0], lines[0]
    assert "error" in lines[0]
    return lines[0]


def _closed_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]   # nothing listens once the socket is closed


@pytest.fixture
def files(tmp_path):
    """A plain file, a folder and a (tiny, not necessarily valid) run log to point commands at."""
    plain = tmp_path / "plain.txt"
    plain.write_text("not a folder\n")
    log = tmp_path / "run.jsonl"
    log.write_text('{"kind": "start"}\n')
    folder = tmp_path / "folder"
    folder.mkdir()
    torn = tmp_path / "torn.jsonl"
    torn.write_text('{"doc": "start", "format": "magctl-ru')
    return {"plain": plain, "log": log, "folder": folder, "tmp": tmp_path, "torn": torn}


# (case id, argv with {plain}/{log}/{folder}/{tmp}/{port} placeholders, what the one line must name)
CASES = [
    ("trials-negative", ["study", "side-push", "--trials", "-5"], "--trials"),
    ("trials-zero", ["study", "side-push", "--trials", "0"], "--trials"),
    ("trials-not-a-number", ["study", "side-push", "--trials", "many"], "--trials"),
    ("reproduce-trials-zero", ["reproduce", "--trials", "0"], "--trials"),
    ("workers-zero", ["study", "servo", "--workers", "0"], "--workers"),
    ("out-is-a-file", ["study", "servo", "--out", "{plain}"], "--out"),
    ("out-under-a-file", ["reproduce", "--out", "{plain}/sub"], "--out"),
    ("out-unwritable", ["study", "servo", "--out", "/proc/magctl-no-such/out"], "--out"),
    ("log-show-a-folder", ["log", "show", "{folder}"], "argument file"),
    ("log-show-missing", ["log", "show", "{tmp}/missing.jsonl"], "argument file"),
    ("log-export-out-missing-folder", ["log", "export", "{log}", "--out", "/nonexistent/x.parquet"], "--out"),
    ("log-export-out-a-folder", ["log", "export", "{log}", "--out", "{folder}"], "--out"),
    ("roughness-nan", ["fluid", "release", "--roughness-nm", "nan"], "--roughness-nm"),
    ("roughness-negative", ["fluid", "sidepush", "--roughness-nm", "-3"], "--roughness-nm"),
    ("gap-nan", ["fluid", "sidepush", "--gap-um", "nan"], "--gap-um"),
    ("radius-inf", ["fluid", "pulloff", "--radius-um", "inf"], "--radius-um"),
    ("rig-unknown-option", ["rig", "run", "--rig", "sim", "--task", "goto", "--target-um", "0", "0",
                            "--option", "no_such_option=1"], "--option"),
    ("rig-option-not-key-value", ["rig", "run", "--rig", "sim", "--task", "front-push", "--option", "ks"],
     "--option"),
    ("rig-duration-negative", ["rig", "run", "--rig", "sim", "--task", "goto", "--target-um", "0", "0",
                               "--duration", "-1"], "--duration"),
    ("rig-max-ticks-zero", ["rig", "run", "--rig", "sim", "--task", "goto", "--target-um", "0", "0",
                            "--max-ticks", "0"], "--max-ticks"),
    ("rig-goto-without-target", ["rig", "run", "--rig", "sim", "--task", "goto"], "--target-um"),
    ("rig-unknown-task", ["rig", "run", "--rig", "sim", "--task", "dance"], "--task"),
    ("rig-log-in-missing-folder", ["rig", "run", "--rig", "sim", "--task", "goto", "--target-um", "0", "0",
                                   "--log", "/nonexistent/run.jsonl"], "--log"),
    ("rig-port-out-of-range", ["rig", "run", "--rig", "tcp://127.0.0.1:99999", "--task", "goto", "--target-um", "0",
                               "0"], "--rig"),
    ("rig-address-without-scheme", ["rig", "run", "--rig", "127.0.0.1:5555", "--task", "goto", "--target-um", "0",
                                    "0"], "--rig"),
    ("log-torn-start", ["log", "show", "{torn}"], "start document is torn"),
    # outside the camera's field of view: refused before the rig is activated
    ("goto-target-off-camera", ["rig", "run", "--rig", "sim", "--task", "goto", "--target-um", "1e9", "1e9"],
     "outside the camera's field of view"),
    ("push-goal-off-camera", ["rig", "run", "--rig", "sim", "--task", "front-push", "--goal-um", "6000", "100"],
     "outside the camera's field of view"),
    ("bench-unknown", ["bench", "--only", "nosuch"], "--only"),
    ("seed-negative", ["study", "side-push", "--seed", "-1"], "--seed"),
    ("seed-not-an-integer", ["rig", "run", "--rig", "sim", "--task", "goto", "--target-um", "0", "0",
                             "--seed", "1.5"], "--seed"),
    ("kc-nan", ["stability", "front", "--kc", "nan"], "--kc"),
    ("servo-kp-zero", ["stability", "servo", "--kp", "0"], "--kp"),
    ("servo-delay-negative", ["stability", "servo", "--delay-frames", "-1"], "--delay-frames"),
    # ranges that keep the analyses finite: an overflowing gain, a latency whose matrix would not fit in memory,
    # a distance far off the slide, a zero scale
    ("kc-overflowing", ["stability", "front", "--kc", "1e308"], "--kc"),
    ("delta0-off-the-slide", ["stability", "front", "--kc", "1", "--delta0-um", "1e300"], "--delta0-um"),
    ("servo-delay-huge", ["stability", "servo", "--delay-frames", "1000000"], "--delay-frames"),
    ("ks-overflowing", ["stability", "side", "--ks", "-1e300"], "--ks"),
    ("side-ratio-zero", ["stability", "side", "--ks", "0.9", "--ratio", "0"], "--ratio"),
    ("side-goal-off-the-slide", ["stability", "side", "--ks", "0.9", "--goal-um", "1e9"], "--goal-um"),
    ("servo-step-huge", ["stability", "servo", "--step-um", "1e12"], "--step-um"),
    ("scheduler-malformed", ["study", "front-push", "--scheduler", "nonsense"], "--scheduler"),
    ("scheduler-unreachable", ["reproduce", "--scheduler", "tcp://127.0.0.1:{port}", "--out", "{tmp}/never"],
     "--scheduler"),
    ("reproduce-only-unknown", ["reproduce", "--only", "nosuch", "--out", "{tmp}/never"], "--only"),
    ("study-unknown", ["study", "nosuch"], "nosuch"),
    ("unknown-flag", ["stability", "servo", "--frobnicate"], "--frobnicate"),
]


@pytest.mark.parametrize("argv, names", [pytest.param(a, n, id=i) for i, a, n in CASES])
def test_bad_input_is_one_line_and_a_nonzero_exit(files, argv, names):
    values = {k: str(v) for k, v in files.items()} | {"port": str(_closed_port())}
    argv = [a.format(**values) for a in argv]
    line = _assert_one_line(_run(argv, files["tmp"]), names)
    assert line.startswith("magctl")
    # nothing was run: no output folder appeared where the command would have written
    assert not (files["tmp"] / "out").exists()
    assert not (files["tmp"] / "never").exists()


def test_output_checks_leave_no_folder_behind(tmp_path):
    """Checking that --out can be created does not leave it created when the command then stops."""
    done = _run(["study", "servo", "--out", str(tmp_path / "a" / "b"), "--trials", "0"], tmp_path)
    _assert_one_line(done, "--trials")
    assert not (tmp_path / "a").exists()


def test_closed_output_pipe_is_one_line_without_traceback(tmp_path):
    """``magctl stability servo | head -2`` with the reader gone before magctl writes."""
    proc = subprocess.Popen([sys.executable, "-m", "magctl", "stability", "servo", "--json"], cwd=tmp_path,
                            env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL)
    proc.stdout.close()             # the reader goes away, as head does after its lines
    err = proc.stderr.read().decode()
    code = proc.wait(timeout=120)
    assert code == 141, (code, err)
    assert "Traceback" not in err
    assert err.splitlines() == ["magctl: error: output closed by the reader (broken pipe)"]


def test_os_errors_and_magctl_errors_are_one_line(monkeypatch, capsys):
    """An OSError or a MagctlError raised inside a command becomes one line and exit code 2."""
    import magctl.cli.stability as stability
    from magctl.cli import main
    from magctl.core.errors import MagctlError

    def disk_full(args):
        raise OSError(28, "No space left on device", "/data/out/report.md")

    monkeypatch.setattr(stability, "cmd_front", disk_full)
    assert main(["stability", "front", "--kc", "1"]) == 2
    err = capsys.readouterr().err
    assert err == "magctl: error: /data/out/report.md: No space left on device\n"

    def two_lines(args):
        raise MagctlError("first line\nsecond line")

    monkeypatch.setattr(stability, "cmd_front", two_lines)
    assert main(["stability", "front", "--kc", "1"]) == 2
    assert capsys.readouterr().err == "magctl: error: first line second line\n"


def test_an_empty_study_folder_is_one_line(tmp_path):
    """$MAGCTL_STUDIES pointing at a folder without studies: not an empty list and exit 0, but one line."""
    empty = tmp_path / "studies"
    empty.mkdir()
    done = subprocess.run([sys.executable, "-m", "magctl", "study", "--list"], cwd=tmp_path,
                          env=_env() | {"MAGCTL_STUDIES": str(empty)}, capture_output=True, text=True, timeout=120)
    line = _assert_one_line(done, str(empty))
    assert "no studies" in line and done.stdout == ""
