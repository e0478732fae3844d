"""Run logs cut into the phases where each plant parameter shows.

:func:`load_runs` reads ``magctl rig run`` logs (:func:`magctl.rig.log.read_log`, schema-checked) into
:class:`Run` arrays and refuses what cannot be identified from: a log of another format, an empty or torn
log, a run with no frames, logs of two different rigs. The cutters then pick, per run:

* :func:`stationary_windows` — frames where the coils have been off long enough for the robot to stand still
  (camera noise);
* :func:`sweep_segments` — the open-loop drive segments of the ``identify`` task (speed against frequency and
  field amplitude, frame lag);
* :func:`side_passes` — each side-push pass (§V-B): the gap the robot actually kept, D_g, and the sphere's
  displacement D_s (eq 22);
* front pushes are read attempt by attempt as the studies read theirs (:mod:`magctl.identify.release`).

A log's event ``k`` holds the observation of frame ``k`` and the command computed from it, which the rig applies
until the next command: command ``k`` drives the robot between frames ``k`` and ``k + 1``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from magctl.control.phases import SidePhase
from magctl.identify.estimate import IdentifyError
from magctl.rig.log import LogError, columns, read_log

_VOLATILE_RIG_KEYS = ("realtime", "scheduling", "address", "endpoint", "session")
"""Keys of a start document's ``rig`` that describe the connection or the scheduling, not the rig itself."""


@dataclass
class Run:
    """One run log as arrays, one row per logged frame (SI)."""

    path: Path
    started: float
    """The start document's ``time_unix``."""
    task: str
    options: dict
    rig: dict
    limits: dict
    stopped: str | None
    """The stop document's exit status; None for a run that crashed (the frames up to the crash are kept)."""
    frame: np.ndarray
    t: np.ndarray
    robot: np.ndarray
    heading: np.ndarray
    spheres: np.ndarray
    lost: np.ndarray
    b_static: np.ndarray
    b_osc: np.ndarray
    freq: np.ndarray
    outputs: dict[str, np.ndarray]

    @property
    def name(self) -> str:
        return self.path.name

    def __len__(self) -> int:
        return len(self.frame)


def _rig_identity(start: dict) -> dict:
    rig = {k: v for k, v in start.get("rig", {}).items() if k not in _VOLATILE_RIG_KEYS}
    return {"rig": rig, "limits": start.get("limits")}


def load_run(path) -> Run:
    """One run log as a :class:`Run`; a :class:`IdentifyError` naming the file when it holds no frames."""
    try:
        log = read_log(path)
    except LogError as err:
        raise IdentifyError(str(err)) from None
    if not log.events:
        raise IdentifyError(f"{log.path}: the run log holds no frames; nothing to identify from")
    c = columns(log)
    n = len(log.events)
    spheres = np.array([e["obs"]["spheres_est_m"] for e in log.events], dtype=float).reshape(n, -1, 2)
    cmd = {k: np.nan_to_num(c[f"cmd_{k}"], nan=0.0) for k in ("b_static_x_T", "b_static_y_T", "b_osc_T", "freq_Hz")}
    outputs = {k[4:]: v for k, v in c.items() if k.startswith("out_")}
    return Run(path=log.path, started=float(log.start["time_unix"]), task=log.start["task"],
               options=log.start.get("options", {}), rig=log.start.get("rig", {}), limits=log.start.get("limits", {}),
               stopped=None if log.stop is None else log.stop["exit_status"],
               frame=c["frame"], t=c["t_s"], robot=np.stack([c["robot_x_m"], c["robot_y_m"]], axis=1),
               heading=c["heading_rad"], spheres=spheres, lost=c["lost"],
               b_static=np.stack([cmd["b_static_x_T"], cmd["b_static_y_T"]], axis=1), b_osc=cmd["b_osc_T"],
               freq=cmd["freq_Hz"], outputs=outputs)


def load_runs(paths) -> list[Run]:
    """Every log of ``paths`` as a :class:`Run`; one :class:`IdentifyError` line if any cannot be used, or if the
    logs come from two different rigs (their start documents describe different rigs or limits)."""
    paths = [Path(p) for p in paths]
    if not paths:
        raise IdentifyError("no run logs given")
    runs, first = [], None
    for p in paths:
        try:
            start = read_log(p).start
        except LogError as err:
            raise IdentifyError(str(err)) from None
        ident = _rig_identity(start)
        if first is None:
            first = (p, ident)
        elif ident != first[1]:
            raise IdentifyError(f"{p} and {first[0]} come from two different rigs (their start documents' rig and "
                                "limits differ); identify one rig's logs at a time")
        runs.append(load_run(p))
    return runs


SAME_SPHERE = 10e-6
"""A run whose sphere 0 starts within this distance of where the previous run (in start time) left it is taken to
push the same sphere (the camera sees positions, not identities)."""


def sphere_groups(runs) -> dict[str, int]:
    """Run name → the id of the sphere (sphere 0) it pushed: runs in start-time order share an id while each starts
    with the sphere where the previous one left it (:data:`SAME_SPHERE`)."""
    ids, current, last = {}, -1, None
    for run in sorted(runs, key=lambda r: r.started):
        if run.spheres.shape[1] == 0:
            continue
        first = run.spheres[0, 0]
        if last is None or np.linalg.norm(first - last) > SAME_SPHERE:
            current += 1
        ids[run.name] = current
        last = run.spheres[-1, 0]
    return ids


def _runs_of(runs, tasks) -> list[Run]:
    return [r for r in runs if r.task in tasks]


def _coils_off(run: Run) -> np.ndarray:
    return (run.b_osc == 0) & (run.freq == 0) & np.all(run.b_static == 0, axis=1)


def stationary_windows(runs, settle: int, min_length: int) -> list[tuple[Run, np.ndarray]]:
    """Frames of each run where the robot stands still: the coils have been off for at least ``settle`` frames
    (the robot has stopped and the camera's lag has passed) and the robot is tracked. Returns (run, frame
    indices) for every window of at least ``min_length`` frames."""
    out = []
    for run in runs:
        off = _coils_off(run)
        # frame k is still when the commands of frames k-settle … k-1 were all "off"
        still = np.zeros(len(run), bool)
        run_len = 0
        for k in range(1, len(run)):
            run_len = run_len + 1 if off[k - 1] else 0
            still[k] = run_len >= settle and not run.lost[k]
        for idx in _spans(still):
            if len(idx) >= min_length:
                out.append((run, idx))
    return out


def fix_noise(windows, skip: int) -> tuple[float, int] | None:
    """The noise of one fix of a resting sphere, per axis [m], and the frames it is measured over: the pooled
    variance of every sphere's estimate over stationary windows (the coils off, so nothing moves the spheres),
    the first ``skip`` frames of each dropped (the tracker settling). None without such frames."""
    ss, dof = 0.0, 0
    for run, idx in windows:
        idx = idx[skip:]
        if len(idx) < 3 or run.spheres.shape[1] == 0:
            continue
        s = run.spheres[idx]                                        # (n, N, 2)
        ss += float(((s - s.mean(axis=0)) ** 2).sum())
        dof += (len(idx) - 1) * s.shape[1] * 2
    if dof == 0:
        return None
    return float(np.sqrt(ss / dof)), dof


def _spans(mask: np.ndarray) -> list[np.ndarray]:
    """Index arrays of the runs of True in ``mask``."""
    idx = np.flatnonzero(mask)
    if idx.size == 0:
        return []
    breaks = np.flatnonzero(np.diff(idx) > 1) + 1
    return np.split(idx, breaks)


@dataclass(frozen=True)
class Segment:
    """An open-loop drive segment of the ``identify`` task: a constant command held over ``frames``."""

    run: Run
    index: int
    frames: np.ndarray
    b_static: np.ndarray
    b_osc: float
    freq: float


def sweep_segments(runs) -> list[Segment]:
    """The drive segments of every ``identify`` run (its ``segment`` output ≥ 0), each with its held command."""
    out = []
    for run in _runs_of(runs, ("identify",)):
        seg = run.outputs.get("segment")
        if seg is None:
            continue
        for idx in _spans(seg >= 0):
            # split where the segment index changes inside a span (back-to-back segments)
            for part in np.split(idx, np.flatnonzero(np.diff(seg[idx]) != 0) + 1):
                k = part[0]
                out.append(Segment(run, int(seg[k]), part, run.b_static[k].copy(), float(run.b_osc[k]),
                                   float(run.freq[k])))
    return out


@dataclass(frozen=True)
class SidePass:
    """One side-push pass (§V-B): the gap the robot kept and what the sphere did."""

    run: Run
    attempt: int
    commanded_gap: float
    gap: float
    """D_g: the sphere's distance from the robot's path (a line fitted to the robot's positions in the pass)."""
    displacement: float
    """D_s: the sphere's net displacement from the pass's first fix (:func:`side_passes`) to the end of the settling
    that follows."""
    frames: tuple[int, int]


def side_passes(runs, min_frames: int = 10, fix_start: float | None = None) -> list[SidePass]:
    """Every pass of every side-push run whose pass and settling were logged to the end.

    ``D_s`` counts from where the robot is ``fix_start`` behind the sphere (``models/identify.toml [side]
    fix_start_um``): at the pass's start the sphere's estimate still follows the repositioning round it."""
    if fix_start is None:
        from magctl.identify.side import fix_start as configured

        fix_start = configured()
    out = []
    for run in _runs_of(runs, ("side-push",)):
        phase, attempt = run.outputs.get("phase"), run.outputs.get("attempt")
        if phase is None or attempt is None:
            continue
        for idx in _spans(phase == SidePhase.PASS):
            if len(idx) < min_frames:
                continue
            a = int(attempt[idx[0]])
            after = np.flatnonzero((np.arange(len(run)) > idx[-1]) & (phase != SidePhase.SETTLE))
            end = int(after[0]) - 1 if after.size else None
            if end is None or end <= idx[-1]:       # the run stopped inside this pass or its settling
                if run.stopped is None or end is None:
                    continue
            sphere0 = run.spheres[idx[0], 0]
            sphere1 = run.spheres[end, 0]
            path = run.robot[idx]
            centre = path.mean(axis=0)
            _, _, vt = np.linalg.svd(path - centre)
            normal = np.array([-vt[0, 1], vt[0, 0]])
            gap = abs(float((sphere0 - centre) @ normal))
            # the first fix: where the robot is `fix_start` behind the sphere along its path
            ahead = path[-1] - path[0]
            along = (path - sphere0) @ (ahead / max(np.linalg.norm(ahead), 1e-300))
            first = int(idx[int(np.argmax(along >= -fix_start))]) if np.any(along >= -fix_start) else int(idx[0])
            sphere0 = run.spheres[first, 0]
            cg = run.outputs.get("gap")
            out.append(SidePass(run, a, float(cg[idx[0]]) if cg is not None else float("nan"), gap,
                                float(np.linalg.norm(sphere1 - sphere0)), (int(idx[0]), end)))
    return out


def attempts_to_converge(runs, task: str) -> list[tuple[Run, int, bool]]:
    """(run, attempts, converged) of every finished run of ``task``: what the logged controller did."""
    from magctl.control.status import Status

    out = []
    for run in _runs_of(runs, (task,)):
        if run.stopped is None or "attempt" not in run.outputs:
            continue
        status = int(run.outputs["status"][-1]) if "status" in run.outputs else -1
        out.append((run, int(run.outputs["attempt"][-1]) + (1 if status == Status.CONVERGED else 0),
                    status == Status.CONVERGED))
    return out
