"""A real Dask scheduler and worker on loopback run the same sweep as serial and local processes, bit for bit."""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from magctl.sweep import SweepError, run_trials
from magctl.testing import drift_trials, failing_trials

pytest.importorskip("distributed")

N_TRIALS = 13
SEED = 20120401
STEPS = 40


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _dask_cli() -> list[str]:
    exe = Path(sys.executable).with_name("dask")
    if exe.exists():
        return [str(exe)]
    found = shutil.which("dask")
    if found:
        return [found]
    pytest.skip("the dask command-line tool is not installed")


def _stop(proc: subprocess.Popen) -> None:
    """Stop a process we started (and the children it started in its own session)."""
    if proc.poll() is not None:
        return
    try:
        os.killpg(proc.pid, signal.SIGTERM)
    except ProcessLookupError:
        return
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)


def _log_tail(path: Path) -> str:
    return path.read_text(errors="replace")[-2000:] if path.exists() else "(no log)"


@pytest.fixture(scope="module")
def dask_scheduler(tmp_path_factory):
    """Address of a running ``dask scheduler`` with one single-threaded ``dask worker``, both on loopback."""
    from distributed import Client

    tmp = tmp_path_factory.mktemp("dask")
    root = Path(__file__).resolve().parents[2]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(root), os.environ.get("PYTHONPATH")])))
    address = f"tcp://127.0.0.1:{_free_port()}"
    procs: list[tuple[subprocess.Popen, Path]] = []

    def start(args: list[str], log: Path) -> None:
        with open(log, "wb") as fh:
            procs.append((subprocess.Popen(args, stdout=fh, stderr=subprocess.STDOUT, env=env, cwd=tmp,
                                           start_new_session=True), log))

    try:
        cli = _dask_cli()
        start([*cli, "scheduler", "--host", "127.0.0.1", "--port", address.rsplit(":", 1)[1], "--no-dashboard"],
              tmp / "scheduler.log")
        start([*cli, "worker", address, "--host", "127.0.0.1", "--nworkers", "1", "--nthreads", "1",
               "--no-dashboard", "--local-directory", str(tmp / "worker"), "--death-timeout", "60"],
              tmp / "worker.log")
        deadline = time.monotonic() + 60
        while True:
            for proc, log in procs:
                if proc.poll() is not None:
                    raise RuntimeError(f"{proc.args[1]} exited with {proc.returncode}:\n{_log_tail(log)}")
            try:
                with Client(address, timeout=2, set_as_default=False) as client:
                    client.wait_for_workers(1, timeout=max(1.0, deadline - time.monotonic()))
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise RuntimeError("Dask scheduler/worker did not come up:\n"
                                       + "\n".join(_log_tail(lg) for _, lg in procs)) from None
                time.sleep(0.5)
        yield address
    finally:
        for proc, _ in reversed(procs):
            _stop(proc)


@pytest.fixture(scope="module")
def reference():
    """The sweep run serially in this process, one trial per chunk."""
    return run_trials(drift_trials, N_TRIALS, seed=SEED, scheduler="serial", chunk_size=1, progress=False,
                      steps=STEPS)


def _assert_identical(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for key in a:
        assert a[key].shape == b[key].shape, key
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)


def test_reference_is_a_real_random_simulation(reference):
    # trials differ from each other, are in trial order, and match a single batch of all trials
    assert list(reference["trial"]) == list(range(N_TRIALS))
    assert len(np.unique(reference["final"][:, 1])) == N_TRIALS
    whole = drift_trials(list(range(N_TRIALS)), SEED, steps=STEPS)
    _assert_identical(reference, whole)


@pytest.mark.parametrize(("workers", "chunk_size"), [(1, None), (1, 4), (2, 1), (2, 5), (2, None)])
def test_local_processes_match_serial(reference, workers, chunk_size):
    got = run_trials(drift_trials, N_TRIALS, seed=SEED, workers=workers, chunk_size=chunk_size, progress=False,
                     steps=STEPS)
    _assert_identical(reference, got)


@pytest.mark.parametrize("chunk_size", [None, 3])
def test_dask_matches_serial(dask_scheduler, reference, chunk_size):
    got = run_trials(drift_trials, N_TRIALS, seed=SEED, scheduler=dask_scheduler, chunk_size=chunk_size,
                     progress=False, steps=STEPS)
    _assert_identical(reference, got)


def test_dask_worker_exception_names_the_chunk(dask_scheduler):
    with pytest.raises(SweepError, match=r"chunk 2 \(trials 8–11\) failed: ValueError: trial 9") as info:
        run_trials(failing_trials, N_TRIALS, seed=SEED, scheduler=dask_scheduler, chunk_size=4, progress=False,
                   fail_on=9, steps=STEPS)
    assert info.value.trials == [8, 9, 10, 11]


def test_reproduce_results_json_is_byte_identical_on_dask_and_local(dask_scheduler, tmp_path):
    """``magctl reproduce`` writes the same results.json bytes from local processes and from Dask.

    The front-push study's trials do matrix products in lockstep batches; its numbers differed in
    the last bits between a Dask worker (one BLAS thread) and this process (one per core) until every
    chunk ran with one BLAS thread.
    """
    from magctl.cli import main

    args = ["reproduce", "--only", "front-push", "--trials", "4", "--no-figures", "--quiet", "--seed", "3"]
    assert main([*args, "--out", str(tmp_path / "local")]) == 0
    assert main([*args, "--out", str(tmp_path / "dask"), "--scheduler", dask_scheduler]) == 0
    local = (tmp_path / "local" / "results.json").read_bytes()
    dask = (tmp_path / "dask" / "results.json").read_bytes()
    assert b'"front-push"' in local and len(local) > 500
    assert local == dask
