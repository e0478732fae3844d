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

The run stops when the task reports ``done`` or ``failed``, when tracking has
been lost for ``lost_timeout`` (the task's tracking guard has already stopped
the robot), on a rig error, or after ``max_ticks`` / ``duration``.
"""

from __future__ import annotations

import gc
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from magctl.config import load_file, models_dir
from magctl.core.compiled import NotCompilable
from magctl.core.errors import MagctlError
from magctl.rig.interface import Lifecycle, Observation, Rig, RigError
from magctl.rig.log import RunLogWriter, descriptor_fields, limits_to_doc, models_snapshot
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

    def stats(self) -> dict[str, Any]:
        def pct(a, q):
            return float(np.percentile(a, q)) if len(a) else None

        return {
            "exit_status": self.exit_status, "reason": self.reason, "ticks": self.ticks, "overruns": self.overruns,
            "jitter_p50_ms": _ms(pct(self.jitter, 50)), "jitter_p99_ms": _ms(pct(self.jitter, 99)),
            "jitter_max_ms": _ms(float(self.jitter.max()) if len(self.jitter) else None),
            "compute_p50_ms": _ms(pct(self.compute, 50)), "compute_p99_ms": _ms(pct(self.compute, 99)),
            "log": self.log_path, "options": self.task_options, **self.final,
        }


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
    """

    def __init__(self, rig: Rig, task: str, options: dict | None = None, *, log_path=None, realtime: bool = True,
                 max_ticks: int | None = None, duration: float | None = None, seed: int = 0, params_path=None,
                 quiet: bool = False, rig_description: dict | None = None, engine: str = "auto"):
        self.rig, self.task_name, self.options = rig, task, dict(options or {})
        self.engine = engine
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
        self.ticks = self.overruns = 0

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
        self._prepare_engine()
        # the controller is built (and compiled) from an observation read before the coils are activated: nothing
        # slow lies between activation and the first tick, where a server's session or watchdog could expire
        first = rig.read()
        task: Task | None = build_task(self.task_name, first, self.options, self.params)
        ctrl = Controller(task, seed=self.seed, engine=self.engine)
        rig.activate()
        writer = None
        old_handlers = self._install_signals()
        jitter, compute = [], []
        status, reason, ticks, overruns, final = "error", "", 0, 0, {}
        try:
            if self.log_path is not None:
                writer = RunLogWriter(self.log_path)
                writer.start(task=task.name, options=task.options, seed=self.seed, rig=self.rig_description,
                             limits=limits_to_doc(rig.limits), models_toml=self._models_snapshot(),
                             params_file=str(self.params_path), period_s=self.period, realtime=self.realtime,
                             argv=sys.argv)
                outs = {n: (p.shape, p.unit) for n, p in task.diagram.outputs.items()
                        if n not in ("b_static", "b_osc", "freq")}
                writer.descriptor(descriptor_fields(rig.n_spheres, outs))
            status, reason, ticks, overruns, final = self._loop(ctrl, writer, jitter, compute)
        except KeyboardInterrupt:
            status, reason, ticks, overruns = "aborted", "interrupted (Ctrl-C)", self.ticks, self.overruns
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
            if writer is not None:
                writer.stop(status, reason, ticks=ticks, overruns=overruns)
        return RunReport(status, reason, ticks, overruns, np.asarray(jitter), np.asarray(compute), final,
                         None if self.log_path is None else str(self.log_path),
                         {} if task is None else task.options)

    def _loop(self, ctrl: Controller, writer, jitter: list, compute: list):
        rig, period, task = self.rig, self.period, ctrl.task
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
                start = clock()
                obs = rig.read()
                t_read = clock()
                if rig.state is not Lifecycle.ACTIVE:
                    return "error", f"rig left 'active': {rig.last_error}", ticks, overruns, final
                if rig.activation != activation:
                    ctrl.reset()
                    activation = rig.activation
                cmd_raw, outs = ctrl.step(obs)
                cmd = rig.limits.clip(cmd_raw)
                t_comp = clock()
                rig.write(cmd)
                t_write = clock()
                j = start - sched if self.realtime else 0.0
                jitter.append(j)
                compute.append(t_comp - t_read)
                st = int(outs["status"][0])
                out_doc = {n: _scalar(v) for n, v in outs.items() if n not in ("b_static", "b_osc", "freq")}
                if writer is not None:
                    writer.event(ticks, obs, cmd_raw, cmd, out_doc,
                                 {"scheduled_s": sched - t0, "start_s": start - t0, "jitter_s": j,
                                  "read_s": t_read - start, "compute_s": t_comp - t_read, "write_s": t_write - t_comp,
                                  "skipped": pending_skips},
                                 activation)
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
                sched += period
                if self.realtime:
                    late = clock() - sched
                    if late > 0:
                        missed = int(late // period) + 1
                        sched += missed * period
                        overruns += missed
                        self.overruns = overruns
                        pending_skips = missed
                        now = clock()
                        if now - last_warn >= self.warn_interval:
                            self._warn(f"overrun: skipped {missed} tick(s) ({overruns} so far)")
                            last_warn = now
        finally:
            gc.enable()
            gc.unfreeze()


def open_rig(address: str, *, n_spheres: int = 1, realtime: bool = True, seed: int = 0, plant: str = "physics",
             reset: bool = False, takeover: bool = False, curve_server_key=None, curve_secret=None,
             scheduling: str = "default scheduling") -> tuple[Rig, dict[str, Any]]:
    """The rig ``magctl rig run --rig ADDRESS`` runs on, and its description for the run log's start document.

    ``"sim"``: an in-process :class:`~magctl.rig.sim.SimRig` of ``n_spheres`` spheres (``plant``, ``seed``;
    ``realtime`` False steps one frame per read, as fast as possible). Otherwise ``address`` is a rig server
    (``tcp://HOST:PORT``) and the rig a :class:`~magctl.rig.client.RigClient` (``reset`` asks a simulated server
    to restart its scene, ``takeover`` takes over another client's session, the ``curve_*`` key files connect
    with CURVE); connecting raises :class:`RigError`. ``scheduling`` (:func:`set_realtime_priority`'s answer) goes
    into the description. The caller closes the rig.
    """
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


def _scalar(v):
    a = np.asarray(v)[0]
    return a.tolist() if a.ndim else (bool(a) if a.dtype == bool else float(a))
