"""Sweeps on the serial executor and local processes: ordering, chunking, errors, cleanup."""

from __future__ import annotations

import socket
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magctl.core.errors import MagctlError
from magctl.core.random import trial_seed_sequence
from magctl.sweep import (
    SchedulerError,
    SerialExecutor,
    SweepError,
    chunk_trials,
    executor_kind,
    run_trials,
)
from magctl.testing import drift_trials, failing_trials


def _first_normals(indices, seed):
    """One N(0,1) draw per trial straight from its SeedSequence: independent of magctl.core.simulate."""
    return np.array([np.random.default_rng(trial_seed_sequence(seed, k)).standard_normal() for k in indices])


@given(n=st.integers(0, 40), chunk=st.integers(1, 12), seed=st.integers(0, 2**32 - 1))
@settings(max_examples=40, deadline=None)
def test_serial_results_independent_of_chunking(n, chunk, seed):
    got = run_trials(_first_normals, n, seed=seed, scheduler="serial", chunk_size=chunk, progress=False)
    want = np.array([np.random.default_rng(np.random.SeedSequence(seed).spawn(max(n, 1))[k]).standard_normal()
                     for k in range(n)])
    np.testing.assert_array_equal(np.asarray(got, dtype=float), want)


@given(n=st.integers(0, 200), chunk=st.integers(1, 50))
def test_chunks_cover_trials_in_order(n, chunk):
    chunks = chunk_trials(n, chunk)
    assert [k for c in chunks for k in c] == list(range(n))
    assert all(1 <= len(c) <= chunk for c in chunks)


def test_simulation_sweep_matches_one_batch():
    whole = drift_trials(list(range(9)), 5, steps=30)
    got = run_trials(drift_trials, 9, seed=5, scheduler="serial", chunk_size=2, progress=False, steps=30)
    for key in whole:
        np.testing.assert_array_equal(got[key], whole[key])
    # the seed matters
    other = run_trials(drift_trials, 9, seed=6, scheduler="serial", progress=False, steps=30)
    assert not np.array_equal(other["final"], whole["final"])


def test_given_executor_is_used_and_left_open():
    with ThreadPoolExecutor(2) as pool:
        a = run_trials(drift_trials, 6, seed=1, executor=pool, chunk_size=4, progress=False, steps=10)
        b = run_trials(drift_trials, 6, seed=1, executor=pool, chunk_size=1, progress=False, steps=10)
        assert pool.submit(int, "3").result() == 3  # still usable
    np.testing.assert_array_equal(a["measured"], b["measured"])


def test_list_results_are_flattened_in_order():
    got = run_trials(_list_trials, 7, seed=0, scheduler="serial", chunk_size=3, progress=False)
    assert got == [f"t{k}" for k in range(7)]


def _list_trials(indices, seed):
    return [f"t{k}" for k in indices]


def _short_trials(indices, seed):
    return {"x": np.zeros(len(indices) - 1)}


def _scalar_trials(indices, seed):
    return 3.0


def test_serial_exception_names_chunk_and_keeps_cause():
    with pytest.raises(SweepError, match=r"chunk 1 \(trials 3–5\) failed: ValueError: trial 4") as info:
        run_trials(failing_trials, 9, seed=0, scheduler="serial", chunk_size=3, progress=False, fail_on=4, steps=5)
    assert info.value.chunk == 1 and info.value.trials == [3, 4, 5]
    assert isinstance(info.value.__cause__, ValueError)
    assert isinstance(info.value, MagctlError)


def test_process_worker_exception_names_chunk():
    with pytest.raises(SweepError, match=r"chunk 0 \(trials 0–4\) failed: ValueError: trial 2"):
        run_trials(failing_trials, 10, seed=0, workers=2, chunk_size=5, progress=False, fail_on=2, steps=5)


@pytest.mark.parametrize(("fn", "message"), [
    (_short_trials, r"chunk 0 \(trials 0–3\) returned 'x' with leading axis 3, expected 4"),
    (_scalar_trials, r"chunk 0 \(trials 0–3\) returned float"),
])
def test_wrong_result_length_is_reported(fn, message):
    with pytest.raises(SweepError, match=message):
        run_trials(fn, 4, seed=0, scheduler="serial", chunk_size=4, progress=False)


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"n_trials": -1}, "n_trials must be a non-negative integer, got -1"),
    ({"n_trials": 2.5}, "n_trials must be a non-negative integer, got 2.5"),
    ({"chunk_size": 0}, "chunk_size must be a positive integer, got 0"),
    ({"workers": 0, "scheduler": None}, "workers must be at least 1, got 0"),
])
def test_bad_arguments(kwargs, message):
    args = {"n_trials": 3, "scheduler": "serial"} | kwargs
    with pytest.raises(SweepError, match=message):
        run_trials(drift_trials, args.pop("n_trials"), seed=0, progress=False, **args)


def test_not_callable():
    with pytest.raises(SweepError, match="is not callable"):
        run_trials("drift", 3, seed=0, scheduler="serial")


def test_scheduler_kinds():
    assert executor_kind(None) == "processes"
    assert executor_kind("processes") == "processes"
    assert executor_kind("serial") == "serial"
    assert executor_kind("tcp://10.0.0.1:8786") == "dask"
    assert executor_kind("10.0.0.1:8786") == "dask"
    with pytest.raises(SchedulerError, match="unknown scheduler 'threads'"):
        executor_kind("threads")


def test_unreachable_scheduler_fails_fast_naming_address():
    with socket.socket() as s:  # a port nobody listens on: bound, never listening
        s.bind(("127.0.0.1", 0))
        address = f"tcp://127.0.0.1:{s.getsockname()[1]}"
        t0 = time.monotonic()
        with pytest.raises(SchedulerError, match=f"cannot reach Dask scheduler at {address} within 1 s"):
            run_trials(drift_trials, 3, seed=0, scheduler=address, timeout=1.0, progress=False)
    assert time.monotonic() - t0 < 8.0


def test_serial_executor_delivers_exceptions_through_future():
    fut = SerialExecutor().submit(int, "x")
    assert isinstance(fut.exception(), ValueError)


def test_zero_trials():
    assert run_trials(drift_trials, 0, seed=0, scheduler="serial") == []


def _pid_trials(indices, seed):
    import os

    return np.full(len(indices), os.getpid())


def test_single_chunk_runs_in_process_without_a_pool():
    import os

    got = run_trials(_pid_trials, 5, seed=0, chunk_size=5, progress=False)  # default scheduler, one chunk
    assert set(got.tolist()) == {os.getpid()}


def test_study_context_sweep(tmp_path):
    from magctl.studies.runner import StudyContext
    from magctl.sweep import run_study_trials

    ctx = StudyContext(out=tmp_path, seed=11, scheduler="serial", quiet=True)
    got = run_study_trials(ctx, drift_trials, 4, steps=8)
    np.testing.assert_array_equal(got["final"], drift_trials([0, 1, 2, 3], 11, steps=8)["final"])


def _inconsistent_trials(indices, seed):
    key = "a" if indices[0] == 0 else "b"
    return {key: np.zeros(len(indices))}


def test_chunks_with_different_keys_are_reported():
    with pytest.raises(SweepError, match=r"chunk 1 \(trials 2–3\) returned \['b'\], but chunk 0 returned \['a'\]"):
        run_trials(_inconsistent_trials, 4, seed=0, scheduler="serial", chunk_size=2, progress=False)


def test_several_sweeps_share_one_executor_with_identical_results():
    from magctl.sweep import run_sweeps

    jobs = {"slow": (drift_trials, 7, {"speed": 50e-6}), "fast": (drift_trials, 5, {"speed": 200e-6})}
    together = run_sweeps(jobs, seed=4, chunk_size=3, scheduler="processes", workers=2, progress=False)
    for key, (fn, n, kw) in jobs.items():
        alone = run_trials(fn, n, seed=4, scheduler="serial", progress=False, **kw)
        assert together[key].keys() == alone.keys()
        for name in alone:
            assert np.array_equal(together[key][name], alone[name])
    first = next(iter(together["slow"]))
    assert not np.array_equal(together["slow"][first][:5], together["fast"][first])


def test_failing_job_is_named():
    from magctl.sweep import run_sweeps

    jobs = {"ok": (drift_trials, 4, {}), "broken": (failing_trials, 4, {"fail_on": 2})}
    with pytest.raises(SweepError, match=r"broken: chunk 1 \(trials 2–3\) failed: ValueError"):
        run_sweeps(jobs, seed=0, chunk_size=2, scheduler="serial", progress=False)
