"""The 30 Hz runtime: read → controller → write on a monotonic clock.

Each tick at its scheduled time ``t0 + k·T``:

1. ``rig.read()`` — the latest observation;
2. ``controller.step(obs)`` — the task diagram, the same blocks as in simulation, B = 1;
3. the command is clipped to the limits and ``rig.write()`` sends it;
4. one event document (observation, raw and sent command, task outputs, timing) is flushed to the log.

A tick that ends after the next one was due makes the loop skip ticks: the
missed ticks are counted as overruns and never replayed; a warning goes to
stderr at most once a second. Garbage collection is frozen and disabled during
the loop. SIGTERM and Ctrl-C stop the loop; whatever the exit, the coils are
zeroed (rig deactivated) and the log gets its stop document.

The run log (:class:`~magctl.rig.log.RunLogWriter`) is created before the coils are activated and capped at
``log_max_bytes`` a file (default: the run's rig.toml ``[log] max_mb``), going on in ``LOG.1``, ``LOG.2``…
(:attr:`RunReport.log_parts`). A log that cannot be written (:class:`~magctl.rig.log.LogError`; a
``LogWriteError`` names the file) ends the run as a rig error does: coils zeroed, exit status ``error``, its
message the reason; a stop document that cannot be written turns the exit status into ``error`` and says so in
the reason.

The run stops when the task reports ``done`` or ``failed``, when tracking has
been lost for ``lost_timeout`` (the task's tracking guard has already stopped
the robot), on a rig error, or after ``max_ticks`` / ``duration``.

**Planning off the frame** (docs/rig.md). A block's Python event — the planned assembly's plan, IPOPT and the
wavefront path, 10-50 ms — does not run inside the tick that raises it: the controller hands it over
(:class:`~magctl.core.kernel.EventRequest`) and a worker thread runs it while the ticks go on, the task holding
the robot (speed cap 0: no oscillating field) as long as its plan is pending. The result is merged before a later
tick's controller step: in simulated time (``realtime=False``, a ``SimRig``/lab rig in lock-step, a ``--lockstep``
server) before the very next tick, waiting for the worker if need be, so a run is a function of its seed and
equals a study's frames; in real time before the first tick that finds it ready. The log's events say at which
frame each plan was requested and applied (``outputs.event_requested``, ``outputs.event_applied``,
``outputs.event_pending``) and the stop document lists them; ``slow_steps`` counts the ticks whose controller step
took longer than the period.
"""

from __future__ import annotations

import gc
import math
import signal
import sys
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from magctl.config import load_file, models_dir
from magctl.core.compiled import NotCompilable
from magctl.core.errors import MagctlError
from magctl.rig.interface import Command, Lifecycle, Observation, Rig, RigError
from magctl.rig.log import (
    LogError,
    RunLogWriter,
    default_part_bytes,
    descriptor_fields,
    event_document,
    limits_to_doc,
    models_snapshot,
    start_document,
)
from magctl.rig.monitor import ControlRequest, RunControls, RunMonitor
from magctl.rig.tasks import Controller, Task, build_task, check_options


@dataclass
class RunReport:
    """What a run did (times in s)."""

    exit_status: str
    reason: str
    ticks: int
    overruns: int
    jitter: np.ndarray = field(repr=False)
    compute: np.ndarray = field(repr=False)
    final: dict[str, Any] = field(default_factory=dict)
    log_path: str | None = None
    task_options: dict[str, Any] = field(default_factory=dict)
    slow_steps: int = 0
    """Ticks whose controller step took longer than the period."""
    events: list[dict[str, Any]] = field(default_factory=list)
    """The events run off the frame (the plans): ``requested`` and ``applied`` tick (log ``seq``; None: never
    applied), ``worker_s`` (None: not finished)."""
    log_parts: list[str] = field(default_factory=list)
    """Every file of the run log, in order: ``LOG``, then ``LOG.1``, ``LOG.2``… past the size cap."""

    def stats(self) -> dict[str, Any]:
        def pct(a, q):
            return float(np.percentile(a, q)) if len(a) else None

        waits = [e["applied"] - e["requested"] for e in self.events if e["applied"] is not None]
        worker = [e["worker_s"] for e in self.events if e["worker_s"] is not None]
        return {
            "exit_status": self.exit_status, "reason": self.reason, "ticks": self.ticks, "overruns": self.overruns,
            "jitter_p50_ms": _ms(pct(self.jitter, 50)), "jitter_p99_ms": _ms(pct(self.jitter, 99)),
            "jitter_max_ms": _ms(float(self.jitter.max()) if len(self.jitter) else None),
            "compute_p50_ms": _ms(pct(self.compute, 50)), "compute_p99_ms": _ms(pct(self.compute, 99)),
            "compute_max_ms": _ms(float(self.compute.max()) if len(self.compute) else None),
            "slow_steps": self.slow_steps,
            **({"events": len(self.events), "event_frames_max": max(waits, default=None),
                "event_worker_max_ms": _ms(max(worker, default=None))} if self.events else {}),
            "log": self.log_path, "log_parts": self.log_parts, "options": self.task_options, **self.final,
        }


@dataclass
class _Pending:
    """An event handed to the worker: the request, the tick that raised it, the worker's future."""

    request: Any
    requested: int
    future: Future
    applied: int | None = None


def _run_timed(request) -> tuple[dict, float]:
    t0 = time.perf_counter()
    result = request.run()
    return result, time.perf_counter() - t0


def simulated_time(rig: Rig) -> bool:
    """Whether ``rig`` advances one frame per read — a :class:`~magctl.rig.station.StationRig` (``SimRig``, a lab
    rig of simulated devices) with ``realtime=False``, or a client of a ``--lockstep`` server — so that a run on it
    is a function of its seed."""
    if getattr(rig, "realtime", True) is False:
        return True
    info = getattr(rig, "server_info", None)
    return bool(isinstance(info, dict) and info.get("lockstep"))


def _ms(x):
    return None if x is None else x * 1e3


class Runtime:
    """Runs one task on one rig.

    Parameters
    ----------
    rig : Rig
        Any rig (configured or not); it is activated at the start and deactivated at the end.
    task : str
        Registry name (see :func:`magctl.rig.tasks.available_tasks`).
    options : dict
        Task options (µm in unit-suffixed keys).
    log_path : path, optional
        Run log to create.
    realtime : bool
        Pace ticks on the monotonic clock (True) or run them back to back (False, for in-process
        simulation as fast as possible).
    max_ticks, duration : optional
        Stop after this many ticks / seconds.
    params_path : path, optional
        Rig parameter file (``models/rig.toml`` by default); its text goes into the log.
    off_frame : bool
        Run the task's Python events (its planner) on a worker thread, off the tick (default); False runs them
        inside the tick that raises them, as a study does (``benchmarks/bench_planning_off_frame.py`` compares).
    log_max_bytes : int, optional
        Size cap of one file of the run log, bytes (``RunLogWriter(max_bytes=…)``: past it the log goes on in
        ``LOG.1``, ``LOG.2``…; 0: no cap). Default: ``[log] max_mb`` of the run's rig parameter file
        (``params_path``), MB = 10⁶ bytes.
    monitor : RunMonitor, optional
        Receives the start document, every event document and the stop document as they are made (the live
        view's feed, :mod:`magctl.rig.monitor`); it must return at once.
    controls : RunControls, optional
        Stop, pause and resume requests from outside (the live view's buttons), taken once a tick.
    """

    def __init__(self, rig: Rig, task: str, options: dict | None = None, *, log_path=None, realtime: bool = True,
                 max_ticks: int | None = None, duration: float | None = None, seed: int = 0, params_path=None,
                 quiet: bool = False, rig_description: dict | None = None, engine: str = "auto",
                 off_frame: bool = True, log_max_bytes: int | None = None, monitor: RunMonitor | None = None,
                 controls: RunControls | None = None):
        self.rig, self.task_name, self.options = rig, task, dict(options or {})
        self.engine = engine
        self.off_frame = bool(off_frame)
        self.log_path = None if log_path is None else Path(log_path)
        self.realtime, self.max_ticks, self.duration, self.seed = realtime, max_ticks, duration, seed
        self.params_path = Path(params_path) if params_path else models_dir() / "rig.toml"
        self.params = load_file(self.params_path)
        rt = self.params.runtime
        self.period = 1.0 / rt.rate
        self.lost_timeout, self.warn_interval, self.spin = rt.lost_timeout, rt.warn_interval, rt.spin
        self.quiet = quiet
        # a status line a second on an interactive stderr, to watch a run converge
        self.progress = not quiet and sys.stderr.isatty()
        self.progress_every = max(1, int(round(rt.rate)))
        self.rig_description = rig_description or {"kind": type(rig).__name__}
        self._stop_reason: str | None = None
        self.ticks = self.overruns = self.slow_steps = 0
        self.lockstep = not realtime
        self._events: list[_Pending] = []
        self.log_max_bytes = None if self.log_path is None else self._log_cap(log_max_bytes)
        self.monitor, self.controls = monitor, controls
        self.paused = False
        self._stop_control: dict | None = None
        self._last_cmd: Command | None = None

    def _log_cap(self, given) -> int:
        """The run log's part size cap in bytes: ``given``, else the run's rig.toml ``[log] max_mb`` (else
        ``models/rig.toml``'s, for a parameter file without a [log] table)."""
        if given is not None:
            if isinstance(given, bool) or not isinstance(given, (int, float)) or not 0 <= given < float("inf"):
                raise LogError(f"{self.log_path}: the log size cap must be a number of bytes >= 0 (0: no cap), "
                               f"got {given!r}")
            return int(given)
        table = self.params.get("log")
        if table is None or "max_mb" not in table:
            return default_part_bytes()
        mb = table.max_mb
        if isinstance(mb, bool) or not isinstance(mb, (int, float)) or not 0 < mb < float("inf"):
            raise LogError(f"{self.params_path}: log.max_mb_1 = {mb!r} must be > 0")
        return int(round(mb * 1e6))

    # --- signals --------------------------------------------------------------------------------
    def request_stop(self, reason: str = "stop requested") -> None:
        """Ask the loop to stop safely after the current tick (thread- and signal-safe)."""
        self._stop_reason = reason

    def _install_signals(self):
        if threading.current_thread() is not threading.main_thread():
            return {}

        def on_term(signum, frame):
            self.request_stop(f"signal {signal.Signals(signum).name}")

        # Ctrl-C too: stopping between ticks leaves no request half-way on the wire
        return {s: signal.signal(s, on_term) for s in (signal.SIGTERM, signal.SIGINT)}

    def _progress(self, t: float, final: dict, outs: dict) -> None:
        robot = ", ".join(f"{x:.0f}" for x in final["robot_um"])
        spheres = " ".join("(" + ", ".join(f"{x:.0f}" for x in s) + ")" for s in final["spheres_um"])
        extra = f" attempt {outs['attempt']:.0f}" if "attempt" in outs else ""
        print(f"[{t:6.1f} s] {final['status']}{extra}  robot ({robot}) µm  spheres {spheres} µm",
              file=sys.stderr, flush=True)

    def _prepare_engine(self) -> None:
        """Compile the task's controller before the coils are live, so the first frame does not wait on numba.

        The compiled code depends on the controller's structure only (its numbers are data), so a
        controller built for a stand-in first observation compiles and runs the code the real one
        will use; errors are left for the real build, after activation, to report.
        """
        if self.engine == "interpreted":
            return
        n = self.rig.n_spheres
        obs = Observation(t=0.0, frame=0, robot_est=np.array([1.0e-3, 1.0e-3]), heading_est=0.0,
                          spheres_est=np.array([[2.0e-3 + 0.6e-3 * i, 1.5e-3] for i in range(n)]).reshape(n, 2),
                          lost=False)
        try:
            ctrl = Controller(build_task(self.task_name, obs, self.options, self.params), seed=self.seed,
                              engine=self.engine)
            ctrl.step(obs)
        except NotCompilable:
            if self.engine == "compiled":
                raise
        except MagctlError:
            pass

    def _models_snapshot(self) -> dict[str, str]:
        """Every parameter file of the models folder, with rig.toml as actually used by this run."""
        files = models_snapshot(models_dir())
        files["rig.toml"] = self.params_path.read_text("utf-8")
        return files

    def _warn(self, msg: str) -> None:
        if not self.quiet:
            print(f"magctl rig: {msg}", file=sys.stderr, flush=True)

    # --- run ------------------------------------------------------------------------------------
    def run(self) -> RunReport:
        rig = self.rig
        check_options(self.task_name, self.options)      # before any coil is activated
        if rig.state is Lifecycle.UNCONFIGURED:
            rig.configure()
        if not self.realtime and getattr(rig, "server_info", None) is not None and not simulated_time(rig):
            # back-to-back ticks against a server on the wall clock would step the controller on repeated frames
            raise RigError("ticks back to back (--fast) need a --lockstep server; this server runs in real time")
        self._prepare_engine()
        # the controller is built (and compiled) from an observation read before the coils are activated: nothing
        # slow lies between activation and the first tick, where a server's session or watchdog could expire
        first = rig.read()
        task: Task | None = build_task(self.task_name, first, self.options, self.params)
        ctrl = Controller(task, seed=self.seed, engine=self.engine, defer_events=self.off_frame)
        # the worker's result is merged at a fixed tick when the rig's frames follow the reads (deterministic)
        self.lockstep = not self.realtime or simulated_time(rig)
        self._events = []
        self.slow_steps = 0
        worker = (ThreadPoolExecutor(max_workers=1, thread_name_prefix="magctl-plan")
                  if ctrl.defer_events and ctrl.has_events else None)
        # the log file is created before the coils are live: one that cannot be (it exists, a part of it exists, its
        # folder is not writable) is a LogError before anything moves
        writer = None if self.log_path is None else RunLogWriter(self.log_path, max_bytes=self.log_max_bytes)
        try:
            rig.activate()
        except BaseException:
            if writer is not None:
                _drop_unwritten(writer)
            raise
        old_handlers = self._install_signals()
        jitter, compute = [], []
        status, reason, ticks, overruns, final = "error", "", 0, 0, {}
        try:
            if writer is not None or self.monitor is not None:
                start = dict(task=task.name, options=task.options, seed=self.seed, rig=self.rig_description,
                             limits=limits_to_doc(rig.limits), models_toml=self._models_snapshot(),
                             params_file=str(self.params_path), period_s=self.period, realtime=self.realtime,
                             argv=sys.argv)
                outs = {n: (p.shape, p.unit) for n, p in task.diagram.outputs.items()
                        if n not in ("b_static", "b_osc", "freq")}
                fields = descriptor_fields(rig.n_spheres, outs)
                if worker is not None:
                    fields |= {"outputs.event_requested": {"shape": [], "unit": "1"},
                               "outputs.event_applied": {"shape": [], "unit": "1"},
                               "outputs.event_pending": {"shape": [], "unit": "bool"},
                               "timing.events_s": {"shape": [], "unit": "s"}}
                if writer is not None:
                    start_doc = writer.start(**start)
                    descriptor = writer.descriptor(fields)
                else:
                    start_doc = start_document("unlogged", **start)
                    descriptor = {"doc": "descriptor", "run": "unlogged", "fields": fields}
                self._monitor("run_started", start_doc, descriptor)
            status, reason, ticks, overruns, final = self._loop(ctrl, writer, jitter, compute, worker)
        except KeyboardInterrupt:
            status, reason, ticks, overruns = "aborted", "interrupted (Ctrl-C)", self.ticks, self.overruns
        except LogError as err:
            # the writer's own error (a LogWriteError names the file: disk full, I/O error): stop as on a rig error
            status, reason, ticks, overruns = "error", _one_line(err), self.ticks, self.overruns
        except RigError as err:
            status, reason, ticks, overruns = "error", str(err), self.ticks, self.overruns
        finally:
            try:
                if rig.state is Lifecycle.ACTIVE:
                    rig.deactivate()
            except RigError as err:
                reason = f"{reason}; zeroing the coils failed: {err}" if reason else f"zeroing failed: {err}"
                status = "error"
            for s, h in old_handlers.items():
                signal.signal(s, h)
            if worker is not None:   # a plan still running finishes on its own; its result is not applied
                worker.shutdown(wait=False, cancel_futures=True)
            events = [{"requested": p.requested, "applied": p.applied,
                       "worker_s": p.future.result()[1] if p.future.done() and not p.future.cancelled()
                       and p.future.exception() is None else None} for p in self._events]
            stop_fields = {"ticks": ticks, "overruns": overruns, "slow_steps": self.slow_steps,
                           **({"events": events} if worker is not None else {}),
                           **({"control": self._stop_control} if self._stop_control is not None else {})}
            if writer is not None:
                try:
                    writer.stop(status, reason, **stop_fields)
                except LogError as err:
                    # the run is over (coils zeroed); its log lacks the stop document, which readers report
                    note = f"the log's stop document was not written: {_one_line(err)}"
                    status, reason = "error", f"{reason}; {note}" if reason else note
            self._monitor("run_stopped", {"doc": "stop", "exit_status": status, "reason": reason,
                                          "n_events": ticks, **stop_fields})
        return RunReport(status, reason, ticks, overruns, np.asarray(jitter), np.asarray(compute), final,
                         None if self.log_path is None else str(self.log_path),
                         {} if task is None else task.options, self.slow_steps, events,
                         [] if writer is None else [str(p) for p in writer.parts])

    def _apply_events(self, ctrl: Controller, pending: list[_Pending], tick: int) -> int:
        """Merge the worker's results before tick ``tick``'s controller step: in lock-step every pending one (the
        request came from an earlier tick; wait for the worker), in real time those that are ready. Returns the
        requesting tick of the last one applied, −1 for none."""
        applied = -1
        for p in list(pending):
            if not (self.lockstep or p.future.done()):
                continue
            result, _seconds = p.future.result()   # an exception of the handler ends the run as in the tick
            ctrl.apply(p.request, result)
            p.applied = tick
            pending.remove(p)
            applied = p.requested
        return applied

    def _loop(self, ctrl: Controller, writer, jitter: list, compute: list, worker: ThreadPoolExecutor | None = None):
        rig, period, task = self.rig, self.period, ctrl.task
        pending: list[_Pending] = []
        slow_steps = 0
        clock = time.perf_counter if not self.realtime else time.monotonic
        activation = rig.activation
        lost_since = None
        overruns = pending_skips = 0
        last_warn = -np.inf
        ticks = 0
        final: dict[str, Any] = {}
        gc.collect()
        gc.freeze()
        gc.disable()
        try:
            t0 = clock()
            sched = t0
            while True:
                if self._stop_reason is not None:
                    return "aborted", self._stop_reason, ticks, overruns, final
                if self.max_ticks is not None and ticks >= self.max_ticks:
                    return "stopped", f"max ticks ({self.max_ticks}) reached", ticks, overruns, final
                if self.duration is not None and sched - t0 >= self.duration:
                    return "stopped", f"duration {self.duration:g} s reached", ticks, overruns, final
                if self.realtime:
                    # sleep to just before the tick, then spin: wake-up latency of sleep() would add jitter
                    wait = sched - clock() - self.spin
                    if wait > 0:
                        time.sleep(wait)
                    while clock() < sched:
                        pass
                control = self._take_controls(ticks) if self.controls is not None else None
                if self._stop_control is not None:    # the operator's stop: a deliberate end, like max ticks
                    return "stopped", self._stop_reason, ticks, overruns, final
                if self._stop_reason is not None:
                    return "aborted", self._stop_reason, ticks, overruns, final
                start = clock()
                obs = rig.read()
                t_read = clock()
                if rig.state is not Lifecycle.ACTIVE:
                    return "error", f"rig left 'active': {rig.last_error}", ticks, overruns, final
                if rig.activation != activation:
                    ctrl.reset()
                    pending.clear()      # plans of the last activation: never applied
                    activation = rig.activation
                if self.paused:
                    self._held_tick(obs, final, writer, control, ticks, start - t0, sched - t0, t_read - start,
                                    activation)
                    ticks += 1
                    self.ticks = ticks
                    sched, overruns, pending_skips, last_warn = self._next_tick(sched, period, clock, overruns,
                                                                                last_warn)
                    continue
                applied = self._apply_events(ctrl, pending, ticks) if pending else -1
                held = bool(pending)     # this step runs with a plan pending: the task holds the robot
                t_events = clock()
                cmd_raw, outs = ctrl.step(obs)
                requested = 0
                if worker is not None:
                    for req in ctrl.take_requests():
                        p = _Pending(req, ticks, worker.submit(_run_timed, req))
                        pending.append(p)
                        self._events.append(p)
                        requested += 1
                cmd = rig.limits.clip(cmd_raw)
                t_comp = clock()
                rig.write(cmd)
                t_write = clock()
                j = start - sched if self.realtime else 0.0
                jitter.append(j)
                compute.append(t_comp - t_events)
                if t_comp - t_events > period:
                    slow_steps += 1
                    self.slow_steps = slow_steps
                st = int(outs["status"][0])
                out_doc = {n: _scalar(v) for n, v in outs.items() if n not in ("b_static", "b_osc", "freq")}
                timing = {"scheduled_s": sched - t0, "start_s": start - t0, "jitter_s": j, "read_s": t_read - start,
                          "compute_s": t_comp - t_events, "write_s": t_write - t_comp, "skipped": pending_skips}
                if worker is not None:
                    out_doc |= {"event_requested": requested, "event_applied": applied, "event_pending": held}
                    timing["events_s"] = t_events - t_read
                if writer is not None or self.monitor is not None:
                    doc = (writer.event if writer is not None else event_document)(
                        ticks, obs, cmd_raw, cmd, out_doc, timing, activation, control=control)
                    if self.monitor is not None:
                        self._monitor("run_frame", doc, self._status(ticks + 1))
                self._last_cmd = cmd
                pending_skips = 0
                ticks += 1
                self.ticks = ticks
                final = {"status": task.status_names.get(st, str(st)), "robot_um": (obs.robot_est * 1e6).tolist(),
                         "spheres_um": (obs.spheres_est * 1e6).tolist(), "outputs": out_doc}
                if self.progress and ticks % self.progress_every == 0:
                    self._progress(ticks * period, final, out_doc)
                if st in task.outcomes:
                    return (*task.outcomes[st], ticks, overruns, final)
                if obs.lost:
                    lost_since = obs.t if lost_since is None else lost_since
                    if obs.t - lost_since >= self.lost_timeout:
                        return ("tracking-lost", f"tracking lost for {obs.t - lost_since:.2f} s; robot stopped",
                                ticks, overruns, final)
                else:
                    lost_since = None
                sched, overruns, pending_skips, last_warn = self._next_tick(sched, period, clock, overruns,
                                                                            last_warn)
        finally:
            gc.enable()
            gc.unfreeze()

    def _next_tick(self, sched: float, period: float, clock, overruns: int, last_warn: float):
        """The next tick's scheduled time; in real time, the ticks already missed are skipped and counted."""
        sched += period
        skipped = 0
        if self.realtime:
            late = clock() - sched
            if late > 0:
                skipped = int(late // period) + 1
                sched += skipped * period
                overruns += skipped
                self.overruns = overruns
                now = clock()
                if now - last_warn >= self.warn_interval:
                    self._warn(f"overrun: skipped {skipped} tick(s) ({overruns} so far)")
                    last_warn = now
        return sched, overruns, skipped, last_warn

    # --- the live view's controls -------------------------------------------------------------------------
    def _take_controls(self, tick: int) -> list[dict] | None:
        """Act on the requests queued since the last tick (before tick ``tick``'s read): a stop sets the stop
        reason (the loop returns before reading: the coils are zeroed before another command is sent), pause/resume
        switch the hold. Returns them for the tick's event document (None: none). The stop document's ``control``
        says which tick took the stop (``before_seq``) and the newest frame its sender had seen (``seen_seq``)."""
        taken: list[ControlRequest] = self.controls.take()
        if not taken:
            return None
        for req in taken:
            if req.action == "stop" and self._stop_reason is None:
                self._stop_reason = f"stop button (by {req.by})"
                self._stop_control = {"action": "stop", "by": req.by, "before_seq": tick,
                                      "seen_seq": req.seen_seq, "waited_s": time.monotonic() - req.t_monotonic}
            elif req.action in ("pause", "resume"):
                self.paused = req.action == "pause"
            self._warn(f"{req.action} by {req.by} before tick {tick}")
        return [{"action": r.action, "by": r.by} for r in taken]

    def _held_tick(self, obs: Observation, final: dict, writer, control, tick: int, start_s: float,
                   scheduled_s: float, read_s: float, activation: int) -> None:
        """A paused tick: the servo's hold — the last command's static field (its heading), no oscillating field —
        sent without stepping the controller, logged ``paused`` with ``cmd_raw`` None (replay skips it)."""
        last = self._last_cmd
        hold = Command(np.zeros(2) if last is None else np.array(last.b_static, dtype=float), 0.0,
                       0.0 if last is None else float(last.freq))
        cmd = self.rig.limits.clip(hold)
        self.rig.write(cmd)
        timing = {"scheduled_s": scheduled_s, "start_s": start_s, "jitter_s": start_s - scheduled_s if self.realtime
                  else 0.0, "read_s": read_s, "compute_s": 0.0, "write_s": 0.0, "skipped": 0}
        outputs = dict(final.get("outputs", {}))
        if writer is not None or self.monitor is not None:
            doc = (writer.event if writer is not None else event_document)(
                tick, obs, None, cmd, outputs, timing, activation, control=control, paused=True)
            if self.monitor is not None:
                self._monitor("run_frame", doc, self._status(tick + 1))

    def _monitor(self, method: str, *docs) -> None:
        """Hand documents to the monitor. A monitor that fails is dropped with one warning: what a run shows must
        never end it (its log is the record)."""
        if self.monitor is None:
            return
        try:
            getattr(self.monitor, method)(*docs)
        except Exception as err:  # noqa: BLE001 - any failure of the view's side
            self.monitor = None
            self._warn(f"the live view failed and is detached; the run goes on ({type(err).__name__}: "
                       f"{_one_line(err)})")

    def _status(self, ticks: int) -> dict[str, Any]:
        """The counters the live view shows beside a frame."""
        trips = getattr(self.rig, "watchdog_trips", None)   # an in-process rig counts its host watchdog's trips
        return {"state": self.rig.state.value, "ticks": ticks, "overruns": self.overruns,
                "slow_steps": self.slow_steps, "paused": self.paused,
                **({"watchdog_trips": trips} if isinstance(trips, int) else {})}


def open_rig(address: str, *, n_spheres: int = 1, realtime: bool = True, seed: int = 0, plant: str = "physics",
             reset: bool = False, takeover: bool = False, curve_server_key=None, curve_secret=None,
             scheduling: str = "default scheduling") -> tuple[Rig, dict[str, Any]]:
    """The rig ``magctl rig run --rig ADDRESS`` runs on, and its description for the run log's start document.

    ``"sim"``: an in-process :class:`~magctl.rig.sim.SimRig` of ``n_spheres`` spheres (``plant``, ``seed``;
    ``realtime`` False steps one frame per read, as fast as possible). A lab file (``*.toml``,
    :mod:`magctl.rig.lab`): a :class:`~magctl.rig.station.StationRig` of its devices, in-process (``realtime``
    False needs its simulated devices: lock-step). Otherwise ``address`` is a rig server
    (``tcp://HOST:PORT``) and the rig a :class:`~magctl.rig.client.RigClient` (``reset`` asks a simulated server
    to restart its scene, ``takeover`` takes over another client's session, the ``curve_*`` key files connect
    with CURVE); connecting raises :class:`RigError`. ``scheduling`` (:func:`set_realtime_priority`'s answer) goes
    into the description. The caller closes the rig.
    """
    if address.endswith(".toml"):
        from magctl.rig.lab import build_station, load_lab
        from magctl.rig.station import StationRig

        cfg = load_lab(address)
        rig = StationRig(lambda: build_station(cfg, lockstep=not realtime), limits=cfg.limits, watchdog=cfg.watchdog,
                         realtime=realtime, period=cfg.period)
        return rig, {**cfg.describe(), "realtime": realtime, "scheduling": scheduling}
    if address == "sim":
        from magctl.rig.sim import SimRig

        rig = SimRig(n_spheres=n_spheres, realtime=realtime, seed=seed, plant=plant)
        return rig, {"kind": "SimRig", "plant": plant, "n_spheres": n_spheres, "realtime": realtime,
                     "scheduling": scheduling}
    from magctl.rig.client import RigClient

    rig = RigClient(address, reset=reset, takeover=takeover, curve_server_key=curve_server_key,
                    curve_secret=curve_secret)
    return rig, {"kind": "RigClient", "address": address, "scheduling": scheduling,
                 "security": "curve" if curve_server_key else "null"}


def set_realtime_priority(priority: int | None) -> str:
    """Run this process under SCHED_FIFO at ``priority`` (Linux, needs CAP_SYS_NICE); returns what happened.

    On a shared machine the tick jitter is dominated by other processes taking the CPU; a
    real-time priority lets the 30 Hz loop (and the rig server) preempt them.
    """
    if not priority:
        return "default scheduling"
    import os

    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(int(priority)))
    except (AttributeError, OSError) as err:
        return f"SCHED_FIFO {priority} refused ({err}); default scheduling"
    return f"SCHED_FIFO {priority}"


def _one_line(err: Exception) -> str:
    """An error's message on one line (a reason of the run report and of the stop document)."""
    return " ".join(str(err).split()) or type(err).__name__


def _drop_unwritten(writer: RunLogWriter) -> None:
    """Close a run log nothing was written to (the run did not start) and remove its empty file."""
    try:
        writer.close()
        if writer.path.stat().st_size == 0:
            writer.path.unlink()
    except (LogError, OSError):
        pass


def _scalar(v):
    """A task output of the (single) trial as JSON: a not-yet-defined value (NaN: e.g. the side push's gap before
    its first attempt) is null, which JSON can carry and a NaN it cannot."""
    a = np.asarray(v)[0]
    if a.dtype == bool:
        return a.tolist() if a.ndim else bool(a)
    return _finite_or_none(a.tolist() if a.ndim else float(a))


def _finite_or_none(x):
    if isinstance(x, list):
        return [_finite_or_none(v) for v in x]
    return x if not isinstance(x, float) or math.isfinite(x) else None
