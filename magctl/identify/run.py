"""``magctl identify``: run logs → an identified parameter folder, a report, and what to run on this rig.

:func:`identify` cuts the logs into phases (:mod:`magctl.identify.phases`), runs every fit on the phases where
its parameter shows, writes the folder (:mod:`magctl.identify.folder`), then asks magctl's own analyses — the
``magctl stability`` commands, run as separate processes with ``--models`` on the new folder, exactly as a user
would run them — for the stable gains and the predicted attempts on this rig, and, given held-out logs,
compares what the identified plant predicts with what those runs did (:mod:`magctl.identify.report`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from magctl.identify import actuation, camera, side
from magctl.identify.estimate import Estimate, IdentifyError, NotIdentified
from magctl.identify.folder import write_folder
from magctl.identify.phases import (
    Run,
    fix_noise,
    load_runs,
    side_passes,
    sphere_groups,
    stationary_windows,
    sweep_segments,
)
from magctl.identify.release import ReleaseFit, fit_release
from magctl.identify.side import SideFit


@dataclass
class Identification:
    """What :func:`identify` found: the estimates, what it could not identify and why, and the fits."""

    runs: list[Run]
    estimates: list[Estimate] = field(default_factory=list)
    not_identified: dict[str, str] = field(default_factory=dict)
    side: SideFit | None = None
    side_data: tuple[np.ndarray, np.ndarray] | None = None
    fix_noise: float = 0.0
    release: ReleaseFit | None = None
    speed: dict | None = None
    timings: dict[str, float] = field(default_factory=dict)

    def get(self, name: str) -> Estimate | None:
        """The estimate of ``file:table.key`` (e.g. ``fluid.toml:domain.depth_mm``), None if not identified."""
        return next((e for e in self.estimates if e.name == name), None)

    def _attempt(self, what: str, fit: Callable[[], list[Estimate] | None]) -> None:
        t0 = time.perf_counter()
        try:
            found = fit()
        except NotIdentified as why:
            self.not_identified[what] = str(why)
        else:
            self.estimates += found or []
        self.timings[what] = time.perf_counter() - t0


def _names(runs) -> str:
    names = sorted({r.name for r in runs})
    return ", ".join(names[:4]) + (f" and {len(names) - 4} more" if len(names) > 4 else "")


def _camera_noise(runs, settings) -> list[Estimate]:
    windows = stationary_windows(runs, settle=int(settings.still_after),
                                 min_length=int(settings.window_min))
    if not windows:
        raise NotIdentified("no stationary frames (coils off for long enough); run the identify task, whose "
                            "first seconds hold the robot still")
    n = sum(len(idx) for _, idx in windows)
    return [camera.noise_from_stationary([run.robot[idx] for run, idx in windows],
                                         f"from {n} stationary frames in {len(windows)} window(s) of "
                                         f"{_names([r for r, _ in windows])}")]


def _sweep_runs(runs) -> list[Run]:
    sweep = [r for r in runs if r.task == "identify"]
    if not sweep:
        raise NotIdentified("no run of the identify task (the open-loop speed sweep): magctl rig run --task identify")
    return sweep


def _latency(runs) -> list[Estimate]:
    run = max(_sweep_runs(runs), key=len)
    return [camera.latency_from_commands(run.t, run.b_static, run.b_osc, run.freq, run.robot, run.heading,
                                         f"from the {len(run)} frames of {run.name}")]


def _drops(runs) -> list[Estimate]:
    return [camera.drop_rate([r.frame for r in runs], f"from the frame numbers of {len(runs)} run(s)")]


def _speed(result: Identification) -> list[Estimate]:
    segs = sweep_segments(_sweep_runs(result.runs))
    rows = []
    for s in segs:
        try:
            rows.append((s, actuation.steady_segment_speed(s.run.t[s.frames], s.run.robot[s.frames])))
        except IdentifyError:
            continue           # a segment too short for a steady speed
    if not rows:
        raise NotIdentified("the identify runs hold no drive segment long enough to measure a speed")
    b_xy = np.array([s.b_static for s, _ in rows])
    b_osc = np.array([s.b_osc for s, _ in rows])
    freq = np.array([s.freq for s, _ in rows])
    speed = np.array([v.speed for _, v in rows])
    n = np.array([v.frames for _, v in rows])
    fit = actuation.speed_curve(b_xy, b_osc, freq, speed, n,
                                f"from {len(rows)} open-loop segments of {_names(_sweep_runs(result.runs))}")
    result.not_identified.update(fit.not_identified)
    result.speed = {"b_osc": b_osc, "freq": freq, "speed": speed, "n": n, "b_xy": b_xy}
    return fit.estimates


def _side(result: Identification, settings) -> list[Estimate]:
    passes = side_passes(result.runs)
    names = sorted({p.run.name for p in passes})
    sphere = sphere_groups(result.runs)
    group = np.array([sphere[p.run.name] for p in passes], dtype=int)
    gaps, disp = np.array([p.gap for p in passes]), np.array([p.displacement for p in passes])
    result.side_data = (gaps, disp)
    noise = fix_noise(stationary_windows(result.runs, settle=int(settings.still_after),
                                         min_length=int(settings.window_min)), skip=int(settings.noise_settle))
    sigma, where = (0.0, "no stationary frames: the fixes' noise taken as 0") if noise is None else (
        noise[0], f"a fix's noise {noise[0] * 1e6:.2f} µm per axis from the resting spheres ({noise[1]} dof)")
    result.fix_noise = sigma
    result.side = side.fit_side(gaps, disp, group, f"from {len(passes)} side passes of {len(names)} run(s), "
                                f"{len(set(group.tolist()))} sphere(s), {where}", fix_noise=sigma)
    return result.side.estimates()


def _release(result: Identification) -> list[Estimate]:
    result.release = fit_release(result.runs)
    return result.release.estimates()


def identify(logs, out: Path | None = None) -> Identification:
    """Identify the plant from ``logs``; with ``out``, write the parameter folder there."""
    from magctl.config import load_model

    settings = load_model("identify")
    runs = load_runs(logs)
    result = Identification(runs)
    result._attempt("camera noise", lambda: _camera_noise(runs, settings.camera))
    result._attempt("camera lag", lambda: _latency(runs))
    result._attempt("dropped frames", lambda: _drops(runs))
    result._attempt("robot speed curve", lambda: _speed(result))
    result._attempt("side-push curve", lambda: _side(result, settings.camera))
    result._attempt("front-push release", lambda: _release(result))
    if out is not None:
        write_folder(out, result.estimates, result.not_identified, [str(r.path) for r in runs])
    return result
