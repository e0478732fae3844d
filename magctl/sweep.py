"""Trial fan-out: serial, local processes, or a Dask cluster behind one executor interface.

A sweep splits trials ``0 … n−1`` into contiguous chunks and hands each chunk to
a trial function ``fn(trial_indices, seed, **kwargs)`` that runs those trials in
lockstep (a batch of ``len(trial_indices)``) and returns one result per trial.
Every trial draws its random numbers from ``SeedSequence(seed, spawn_key=(k, …))``
(:mod:`magctl.core.random`; ``simulate(..., trials=indices, seed=seed)`` does
this), so trial ``k``'s result is the same whatever the executor, the chunk size
and the number of workers.

Executors (all ``concurrent.futures.Executor``):

- ``"serial"`` — :class:`SerialExecutor`, in this process (debugging, tests);
- ``None`` / ``"processes"`` — ``ProcessPoolExecutor`` with ``workers`` processes
  (default: the CPUs this process may use);
- ``"tcp://HOST:PORT"`` (any Dask address) — ``distributed.Client(addr).get_executor()``.

Functions sent to processes or Dask workers are pickled by reference: define
them in an importable module (see :mod:`magctl.testing`).
"""

from __future__ import annotations

import math
import multiprocessing
import os
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Executor, Future, ProcessPoolExecutor, wait
from contextlib import contextmanager
from typing import Any

import numpy as np

from magctl.core.errors import MagctlError
from magctl.core.progress import trial_counter

SERIAL = "serial"
PROCESSES = "processes"
DEFAULT_CONNECT_TIMEOUT_S = 5.0


class SweepError(MagctlError):
    """A chunk of trials failed (or returned something that cannot be combined).

    Attributes
    ----------
    chunk : int
        Index of the failing chunk.
    trials : list of int
        Global trial indices of that chunk.
    """

    def __init__(self, message: str, chunk: int, trials: Sequence[int]):
        self.chunk, self.trials = int(chunk), [int(k) for k in trials]
        super().__init__(message)


class SchedulerError(MagctlError):
    """The Dask scheduler cannot be reached, has no workers, or the address is malformed."""


class SerialExecutor(Executor):
    """Runs each submitted call at once, in this process; the returned future is already done."""

    def submit(self, fn, /, *args, **kwargs) -> Future:
        fut: Future = Future()
        try:
            fut.set_result(fn(*args, **kwargs))
        except BaseException as exc:  # delivered through the future, as any executor does
            fut.set_exception(exc)
        return fut


def default_workers() -> int:
    """Number of CPUs this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def executor_kind(scheduler: str | None) -> str:
    """``"serial"``, ``"processes"`` or ``"dask"`` for a ``scheduler`` argument, or :class:`SchedulerError`."""
    if scheduler is None or scheduler == PROCESSES:
        return PROCESSES
    if scheduler == SERIAL:
        return SERIAL
    if isinstance(scheduler, str) and ("://" in scheduler or scheduler.rpartition(":")[2].isdigit()):
        return "dask"
    raise SchedulerError(
        f"unknown scheduler {scheduler!r}: use 'serial', 'processes' (or None) or a Dask address "
        f"such as tcp://127.0.0.1:8786"
    )


PRELOAD = ("__main__", "numpy", "magctl.core")
"""Modules the fork server imports once, so each worker starts without importing them again."""


def _process_context(start_method: str | None = None):
    """``forkserver`` by default: workers never inherit the parent's threads (tqdm, a Dask client) holding a
    lock, as ``fork`` children can; like ``spawn`` it needs scripts to guard their entry point with
    ``if __name__ == "__main__":``."""
    methods = multiprocessing.get_all_start_methods()
    method = start_method or ("forkserver" if "forkserver" in methods else "spawn")
    if method not in methods:
        raise SweepError(f"start method {method!r} is not available here; available: {methods}", -1, [])
    ctx = multiprocessing.get_context(method)
    if method == "forkserver":
        ctx.set_forkserver_preload(list(PRELOAD))
    return ctx


def connect_dask(address: str, timeout: float = DEFAULT_CONNECT_TIMEOUT_S):
    """A ``distributed.Client`` on ``address`` with at least one worker, or :class:`SchedulerError`.

    Parameters
    ----------
    address : str
        Scheduler address, e.g. ``tcp://127.0.0.1:8786``.
    timeout : float
        Seconds allowed to connect, and again to wait for a first worker.
    """
    try:
        from distributed import Client
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise SchedulerError(
            f"Dask scheduler {address} requested but distributed is not installed: pip install 'magctl[dask]'"
        ) from exc
    try:
        client = Client(address, timeout=timeout, set_as_default=False)
    except Exception as exc:
        raise SchedulerError(
            f"cannot reach Dask scheduler at {address} within {timeout:g} s ({type(exc).__name__}: {exc})"
        ) from exc
    try:
        if not client.nthreads():
            client.wait_for_workers(1, timeout=timeout)
    except Exception as exc:
        client.close()
        raise SchedulerError(f"Dask scheduler at {address} has no workers after {timeout:g} s") from exc
    return client


@contextmanager
def open_executor(scheduler: str | None = None, workers: int | None = None,
                  timeout: float = DEFAULT_CONNECT_TIMEOUT_S, start_method: str | None = None,
                  ) -> Iterator[tuple[Executor, int]]:
    """The executor for ``scheduler`` and its parallelism; shut down (or disconnected) on exit.

    Parameters
    ----------
    scheduler : str, optional
        ``"serial"``, ``"processes"`` / None, or a Dask scheduler address.
    workers : int, optional
        Local processes (default: the CPUs this process may use).
    timeout : float
        Seconds allowed to reach a Dask scheduler and see a worker there.
    start_method : str, optional
        multiprocessing start method of local processes (default ``forkserver``).

    Yields
    ------
    (Executor, int)
        The executor and the number of chunks it runs at once.
    """
    kind = executor_kind(scheduler)
    if workers is not None and int(workers) < 1:
        raise SweepError(f"workers must be at least 1, got {workers}", -1, [])
    if kind == SERIAL:
        yield SerialExecutor(), 1
    elif kind == PROCESSES:
        n = int(workers) if workers is not None else default_workers()
        pool = ProcessPoolExecutor(max_workers=n, mp_context=_process_context(start_method))
        try:
            yield pool, n
        finally:
            pool.shutdown(wait=True, cancel_futures=True)
    else:
        client = connect_dask(scheduler, timeout)
        try:
            yield client.get_executor(pure=False), max(1, sum(client.nthreads().values()))
        finally:
            client.close()


def chunk_trials(n_trials: int, chunk_size: int) -> list[list[int]]:
    """Contiguous chunks ``[0 … c−1], [c … 2c−1], …`` covering ``0 … n_trials−1``."""
    return [list(range(a, min(a + chunk_size, n_trials))) for a in range(0, n_trials, chunk_size)]


def default_chunk_size(n_trials: int, parallelism: int) -> int:
    """About four chunks per worker: big lockstep batches, yet balanced load and a moving progress bar."""
    return max(1, math.ceil(n_trials / (4 * max(1, parallelism))))


def _call_chunk(fn: Callable, indices: list[int], seed: int, kwargs: dict) -> Any:
    """Run one chunk with BLAS on one thread, wherever it runs.

    A multi-threaded BLAS splits a matrix product differently with the number of its threads, and
    the last bits of the result follow the split. Dask workers start with one BLAS thread
    (``OPENBLAS_NUM_THREADS=1`` …), local processes and this process with one per core, so without
    this the same trial differed in its last bits between executors. One thread everywhere makes a
    trial's result the same bit for bit whatever ran it (the per-trial batches are small; BLAS
    threads do not pay for themselves here).
    """
    from threadpoolctl import threadpool_limits

    # kwargs travel as one positional dict so none of them is taken for an executor option
    with threadpool_limits(limits=1, user_api="blas"):
        return fn(indices, seed, **kwargs)


def _chunk_length(result: Any, i: int, indices: list[int]) -> None:
    """Check that a chunk returned one entry per trial, naming the offender otherwise."""
    want = len(indices)
    where = f"chunk {i} (trials {indices[0]}–{indices[-1]})"
    if isinstance(result, dict):
        for key, value in result.items():
            n = np.shape(value)[0] if np.ndim(value) else None
            if n != want:
                raise SweepError(f"{where} returned {key!r} with leading axis {n}, expected {want} (one per trial)",
                                 i, indices)
    elif isinstance(result, (list, tuple, np.ndarray)):
        if len(result) != want:
            raise SweepError(f"{where} returned {len(result)} results for {want} trials", i, indices)
    else:
        raise SweepError(f"{where} returned {type(result).__name__}; a trial function must return a dict of "
                         f"arrays, an array or a list with one entry per trial", i, indices)


def _combine(results: list, chunks: list[list[int]]):
    if not results:
        return []
    first = results[0]
    for i, (res, idx) in enumerate(zip(results, chunks)):
        kinds_match = isinstance(res, dict) == isinstance(first, dict)
        if not kinds_match or (isinstance(res, dict) and res.keys() != first.keys()):
            got = sorted(res) if isinstance(res, dict) else type(res).__name__
            want = sorted(first) if isinstance(first, dict) else type(first).__name__
            raise SweepError(f"chunk {i} (trials {idx[0]}–{idx[-1]}) returned {got}, but chunk 0 returned {want}",
                             i, idx)
    if isinstance(first, dict):
        return {k: np.concatenate([np.asarray(r[k]) for r in results], axis=0) for k in first}
    if isinstance(first, np.ndarray):
        return np.concatenate(results, axis=0)
    return [x for r in results for x in r]


def run_trials(fn: Callable, n_trials: int, *, seed: int, chunk_size: int | None = None,
               scheduler: str | None = None, workers: int | None = None, executor: Executor | None = None,
               progress: bool = True, desc: str = "trials", timeout: float = DEFAULT_CONNECT_TIMEOUT_S,
               **kwargs) -> dict[str, np.ndarray] | np.ndarray | list:
    """Run trials ``0 … n_trials−1`` of ``fn`` in chunks and return their results in trial order.

    Parameters
    ----------
    fn : callable
        ``fn(trial_indices: list[int], seed: int, **kwargs)`` runs those trials as one
        batch and returns a dict of arrays with leading axis ``len(trial_indices)``,
        an array with that leading axis, or a list of per-trial results. It must be
        importable (module level) for processes and Dask.
    n_trials : int
        Number of trials.
    seed : int
        Root seed, passed unchanged to every chunk; trial ``k`` must draw from
        ``SeedSequence(seed, spawn_key=(k, …))`` for results to be executor-independent.
    chunk_size : int, optional
        Trials per call of ``fn``; default about four chunks per worker.
    scheduler : str, optional
        ``"serial"``, ``"processes"`` / None (local processes) or a Dask address.
    workers : int, optional
        Local worker processes (default: CPU count); with ``executor``, the number
        of chunks it runs at once (default: its ``max_workers`` or the CPU count).
    executor : concurrent.futures.Executor, optional
        Use this executor instead (not shut down here); overrides ``scheduler``.
        Open one with :func:`open_executor` to share a pool between sweeps.
    progress : bool
        Show a progress bar on stderr (only when stderr is a terminal).
    desc : str
        Progress bar label.
    timeout : float
        Seconds allowed to reach a Dask scheduler (and to see a worker there).
    **kwargs
        Passed to every call of ``fn``.

    Returns
    -------
    dict of str to ndarray, ndarray or list
        Per-trial results of all chunks concatenated in trial order.

    Raises
    ------
    SweepError
        A chunk raised (chained as ``__cause__``) or returned the wrong number of
        results; the message names the chunk and its trials.
    SchedulerError
        Unknown scheduler, or a Dask scheduler not reachable within ``timeout``.
    """
    if not callable(fn):
        raise SweepError(f"trial function {fn!r} is not callable", -1, [])
    if isinstance(n_trials, bool) or int(n_trials) != n_trials or n_trials < 0:
        raise SweepError(f"n_trials must be a non-negative integer, got {n_trials!r}", -1, [])
    if chunk_size is not None and (int(chunk_size) != chunk_size or chunk_size < 1):
        raise SweepError(f"chunk_size must be a positive integer, got {chunk_size!r}", -1, [])
    n_trials, seed = int(n_trials), int(seed)
    if executor is not None:
        return _run(executor, _parallelism(executor, workers), fn, n_trials, seed, chunk_size, progress, desc,
                    kwargs)
    guess = int(chunk_size or default_chunk_size(n_trials, workers or default_workers()))
    if scheduler is None and n_trials <= guess:
        # a single chunk gains nothing from a pool; skip its start-up (same results: per-trial seeds)
        scheduler = SERIAL
    with open_executor(scheduler, workers, timeout) as (ex, parallelism):
        # the chunks (so each trial's batch) do not depend on the executor: a Dask cluster of any size
        # computes the same batches as this machine's processes
        return _run(ex, parallelism, fn, n_trials, seed, guess, progress, desc, kwargs)


def _parallelism(executor: Executor, workers: int | None) -> int:
    if workers is not None:
        return max(1, int(workers))
    if isinstance(executor, SerialExecutor):
        return 1
    client = getattr(executor, "_client", None)  # distributed's ClientExecutor
    if client is not None:
        return max(1, sum(client.nthreads().values()))
    return int(getattr(executor, "_max_workers", 0)) or default_workers()


def run_study_trials(ctx, fn: Callable, n_trials: int, *, desc: str = "trials", chunk_size: int | None = None,
                     **kwargs):
    """:func:`run_trials` with the seed, scheduler, workers and quietness of a study context."""
    return run_trials(fn, n_trials, seed=ctx.seed, chunk_size=chunk_size, scheduler=ctx.scheduler,
                      workers=ctx.workers, progress=not ctx.quiet, desc=desc, **kwargs)


def run_sweeps(jobs: dict, *, seed: int, chunk_size: int | None = None, scheduler: str | None = None,
               workers: int | None = None, progress: bool = True, desc: str = "trials",
               timeout: float = DEFAULT_CONNECT_TIMEOUT_S) -> dict:
    """Several sweeps on one executor at once: ``jobs`` maps a key to ``(fn, n_trials, kwargs)``.

    Chunks of all jobs share the workers, so many small sweeps (one per controller, say)
    keep every worker busy with large lockstep batches. Returns ``{key: results}`` with
    each job's per-trial results in trial order, exactly as :func:`run_trials` would.
    """
    with open_executor(scheduler, workers, timeout) as (ex, parallelism):
        return _run_jobs(ex, parallelism, jobs, int(seed), chunk_size, progress, desc,
                         chunking=workers or default_workers())


def _run(ex: Executor, parallelism: int, fn, n_trials, seed, chunk_size, progress, desc, kwargs):
    return _run_jobs(ex, parallelism, {None: (fn, n_trials, kwargs)}, seed, chunk_size, progress, desc)[None]


def _run_jobs(ex: Executor, parallelism: int, jobs: dict, seed: int, chunk_size, progress, desc,
              chunking: int | None = None) -> dict:
    chunks = {key: chunk_trials(n, int(chunk_size or default_chunk_size(n, chunking or parallelism)))
              for key, (_, n, _) in jobs.items()}
    results = {key: [None] * len(c) for key, c in chunks.items()}
    items = [(key, i, idx) for key, c in chunks.items() for i, idx in enumerate(c)]
    # at most two chunks per worker in flight: bounded memory, and the serial executor still shows progress
    todo = iter(items)
    pending: dict[Future, tuple] = {}

    def submit_next() -> None:
        for key, i, idx in todo:
            fn, _, kwargs = jobs[key]
            pending[ex.submit(_call_chunk, fn, idx, seed, kwargs)] = (key, i, idx)
            return

    for _ in range(2 * parallelism):
        submit_next()
    bar = trial_counter(sum(len(idx) for _, _, idx in items), desc=desc, quiet=not progress)
    try:
        while pending:
            done, _ = wait(list(pending), return_when=FIRST_COMPLETED)
            for fut in done:
                key, i, idx = pending.pop(fut)
                where = "" if key is None else f"{key}: "
                try:
                    res = fut.result()
                except Exception as exc:
                    raise SweepError(
                        f"{where}chunk {i} (trials {idx[0]}–{idx[-1]}) failed: {type(exc).__name__}: {exc}", i, idx
                    ) from exc
                _chunk_length(res, i, idx)
                results[key][i] = res
                bar.update(len(idx))
                submit_next()
    finally:
        for fut in pending:
            fut.cancel()
        bar.close()
    return {key: _combine(results[key], chunks[key]) for key in jobs}
