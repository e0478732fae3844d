"""The identification experiment: the runs to make on a rig (:func:`plan`) and making them (:func:`run_experiment`).

The default plan (``models/identify.toml`` ``[experiment]``), run in this order on one rig, each run starting where
the previous one left the robot and the sphere:

1. ``sweep`` — the ``identify`` task: the open-loop speed sweep (:mod:`magctl.control.excitation`); the camera
   and tracker fits use its coils-off hold, the actuation fit its drive segments. The robot ends near its start.
2. ``front-<length>um`` — a ``front-push`` run for each of ``front_goals_um`` (at most ``front_attempts_count``
   attempts): the release ``D_p,r``. Its goal lies ``length`` from the sphere along the camera field's long axis,
   towards the field's centre (:attr:`RunSpec.push_length`), from where the previous run left the sphere: the
   pushes go to and fro about the centre and the sphere stays in the field. (The task's own default goal, beyond
   the sphere away from the robot, aims each push wherever the previous one left the robot; on the simulated rig
   that took the sphere to the field's edge and the robot out of it.)
3. ``side-<gap>um`` — a ``side-push`` run at each gap of ``side_gaps_um`` (``fixed_gap``), ``passes_per_gap_count``
   passes each (``max_attempts``): the side-push curve ``D_s(D_g)``. A run that ends at its attempt limit has
   made its passes; that is the normal end of a fixed-gap run. Each run's default goal lies to the left of the
   robot's line through the sphere, and each ends with the robot past the sphere, so the runs push the sphere
   to and fro.

The plan holds no positions: the side pushes' goals are the task's defaults, resolved from each run's first
observation, and the front pushes' goals are resolved by :func:`run_experiment` from the previous run's last one.
It runs on any rig whose scene the sweep can start from (the robot at least ``models/push.toml [common]
clearance_um`` from the sphere, ``field_margin_um`` inside the field, with room for the squares: ``magctl rig
serve-sim``'s default scene).
:func:`run_experiment` runs the plan through the code path
of ``magctl rig run`` (:func:`magctl.rig.runtime.open_rig`, :class:`magctl.rig.runtime.Runtime`), one run log
per run, ``NN-name.jsonl``; it stops at the first run that ends otherwise than its spec expects.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from magctl.config import Params, load_model
from magctl.core.errors import MagctlError
from magctl.rig.interface import RigError
from magctl.rig.runtime import RunReport, Runtime, open_rig
from magctl.rig.tasks import check_options
from magctl.sensing.camera import field_of_view

__all__ = ["ExperimentError", "RunSpec", "goal_towards_centre", "log_name", "plan", "run_experiment"]


class ExperimentError(MagctlError):
    """The experiment cannot be planned or a run of it ended in a fault; the message is one line."""


@dataclass(frozen=True)
class RunSpec:
    """One run of the experiment.

    Attributes
    ----------
    name : str
        Short name, used in the log's file name (``03-side-380um``).
    task : str
        Rig task (:func:`magctl.rig.tasks.available_tasks`).
    options : dict
        The task's options, unit-suffixed keys as ``magctl rig run --option`` takes them.
    ends : tuple of str
        The task statuses (:attr:`magctl.control.status.Status.label`) that end this run normally; any other end
        (a safety stop, a lost sphere or robot, a rig error) stops the experiment.
    push_length : float, optional
        A push task's goal, m from sphere 0 along the camera field's long axis towards its centre
        (:func:`goal_towards_centre`), resolved when the run starts from where the previous run left the sphere
        and given to the task as its ``goal_um`` option (which the run log records).
    """

    name: str
    task: str
    options: dict[str, Any] = field(default_factory=dict)
    ends: tuple[str, ...] = ("converged",)
    push_length: float | None = None

    def resolved(self, spheres) -> dict[str, Any]:
        """The options with the goal of :attr:`push_length` from the spheres' positions ``spheres`` (N, 2) m."""
        if self.push_length is None:
            return dict(self.options)
        goal = goal_towards_centre(np.asarray(spheres, dtype=float).reshape(-1, 2)[0], self.push_length)
        return {**self.options, "goal_um": [round(x * 1e6, 3) for x in goal]}


def goal_towards_centre(sphere, length: float, span: tuple[float, float] | None = None) -> np.ndarray:
    """The point ``length`` m from ``sphere`` along the camera field's long axis (``models/camera.toml``), towards
    the field's centre (the +axis direction from the centre itself)."""
    w, h = span if span is not None else field_of_view()
    axis = 0 if w >= h else 1
    goal = np.array(sphere, dtype=float).reshape(2)
    goal[axis] += length if goal[axis] <= (w, h)[axis] / 2 else -length
    return goal


def plan(params: Params | None = None) -> list[RunSpec]:
    """The experiment's runs, in order (module docstring), from ``params`` (``load_model("identify")``)."""
    e = (params if params is not None else load_model("identify")).experiment
    min_gap = float(load_model("push").side.min_gap)
    passes, attempts = _count(e, "passes_per_gap"), _count(e, "front_attempts")
    specs = [RunSpec("sweep", "identify", {})]
    for length in _lengths(e, "front_goals"):
        specs.append(RunSpec(f"front-{length * 1e6:.0f}um", "front-push", {"max_attempts": attempts},
                             ("converged", "attempt_limit"), push_length=length))
    for gap in _lengths(e, "side_gaps"):
        if gap < min_gap:
            raise ExperimentError(f"identify.toml [experiment] side_gaps_um: {gap * 1e6:g} µm is below "
                                  f"models/push.toml [side] min_gap_um ({min_gap * 1e6:g} µm), where the robot "
                                  f"touches the sphere")
        specs.append(RunSpec(f"side-{gap * 1e6:.0f}um", "side-push", {"fixed_gap_um": _um(gap),
                                                                       "max_attempts": passes},
                             ("converged", "attempt_limit")))
    return _numbered(specs)


def _numbered(specs: list[RunSpec]) -> list[RunSpec]:
    """Repeated names (a push length run twice) get ``-2``, ``-3`` … from their second run on."""
    seen: dict[str, int] = {}
    out = []
    for s in specs:
        seen[s.name] = seen.get(s.name, 0) + 1
        out.append(s if seen[s.name] == 1 else dataclasses.replace(s, name=f"{s.name}-{seen[s.name]}"))
    return out


def _count(e: Params, name: str) -> int:
    v = e[name]
    if isinstance(v, bool) or float(v) != int(v) or v < 1:
        raise ExperimentError(f"identify.toml [experiment] {name}_count = {v!r} must be a whole number ≥ 1")
    return int(v)


def _lengths(e: Params, name: str) -> list[float]:
    v = np.atleast_1d(np.asarray(e[name], dtype=float))
    if v.ndim != 1 or not np.all(v > 0):
        raise ExperimentError(f"identify.toml [experiment] {name}_um must be a list of lengths > 0")
    return [float(x) for x in v]


def _um(length: float) -> float:
    """A length in m as µm, rounded off the float noise of the file's µm → m conversion."""
    return round(length * 1e6, 6)


def log_name(index: int, spec: RunSpec) -> str:
    """``NN-name.jsonl``, ``index`` counted from 1."""
    return f"{index:02d}-{spec.name}.jsonl"


Progress = Callable[[int, int, RunSpec, "RunReport | None"], None]


def run_experiment(rig: str, out_dir: Path, seed: int = 0, n_spheres: int = 1, plant: str = "physics",
                   progress: Progress | None = None, *, specs: Sequence[RunSpec] | None = None,
                   engine: str = "auto", quiet: bool = True, log_max_bytes: int | None = None) -> list[Path]:
    """Run the experiment's runs in order on one rig; returns the logs written.

    Parameters
    ----------
    rig : str
        ``"sim"``: an in-process simulated rig (``n_spheres``, ``plant``, ``seed``), kept across the runs and
        stepped as fast as it computes; or a rig server's address (``tcp://HOST:PORT``), run at 30 Hz — or as
        fast as it answers when the server runs in lock-step (``serve-sim --lockstep``: simulated time).
    out_dir : Path
        Folder for the logs ``NN-name.jsonl`` (created); a log that exists already is an error before any run.
    seed : int
        Root seed of the simulated rig's plant and of every run's controller.
    progress : callable, optional
        ``progress(i, n, spec, report)``: before run ``i`` of ``n`` (``report`` None) and after it (its
        :class:`~magctl.rig.runtime.RunReport`).
    specs : sequence of RunSpec, optional
        The runs (:func:`plan` by default).
    engine : str
        Controller engine of every run (``magctl rig run --engine``).
    quiet : bool
        Silence the runtime's warnings on stderr.
    log_max_bytes : int, optional
        Size cap of one file of each run log (``Runtime(log_max_bytes=…)``; ``magctl rig run --log-max-mb``): past
        it a log goes on in ``NN-name.jsonl.1``… Default ``models/rig.toml`` [log] ``max_mb``; 0: no cap.

    Raises
    ------
    ExperimentError
        One line: a run ended otherwise than its spec's ``ends`` (safety stop, fault, rig error), or its task
        could not be built. The logs of the runs before it, and its own, are kept.
    """
    specs = plan() if specs is None else list(specs)
    out_dir = Path(out_dir)
    paths = [out_dir / log_name(i, s) for i, s in enumerate(specs, 1)]
    for p in paths:
        if p.exists():
            raise ExperimentError(f"{p}: exists; run logs are never overwritten (give an empty folder)")
    for i, s in enumerate(specs):  # every task and option checked before the rig is touched
        try:
            check_options(s.task, s.options)
        except MagctlError as err:
            raise ExperimentError(f"run {s.name!r}: {err}") from None
        if s.push_length is not None and i == 0:
            raise ExperimentError(f"run {s.name!r}: a push towards the field's centre needs a run before it (the "
                                  f"sphere's position)")
    out_dir.mkdir(parents=True, exist_ok=True)
    sim = rig == "sim"
    try:
        handle, desc = open_rig(rig, n_spheres=n_spheres, realtime=False, seed=seed, plant=plant)
    except RigError as err:
        raise ExperimentError(f"identify experiment: {err}") from None
    # a lock-step server steps its plant once per read: simulated time, so the runs need not wait for the clock
    try:
        realtime = not sim and not handle.call("hello").get("lockstep", False)
    except RigError as err:
        handle.close()
        raise ExperimentError(f"identify experiment: {err}") from None
    written: list[Path] = []
    spheres = None
    try:
        for i, (spec, path) in enumerate(zip(specs, paths, strict=True), 1):
            if progress is not None:
                progress(i, len(specs), spec, None)
            if spec.push_length is not None and not spheres:
                raise ExperimentError(f"{path.name}: no sphere position from the run before it to aim the push at")
            try:
                options = spec.resolved(np.asarray(spheres, dtype=float) * 1e-6)
                report = Runtime(handle, spec.task, options, log_path=path, realtime=realtime, seed=seed,
                                 quiet=quiet, rig_description=desc, engine=engine,
                                 log_max_bytes=log_max_bytes).run()
            except MagctlError as err:
                raise ExperimentError(f"{path.name}: {spec.task}: {err}") from None
            spheres = report.final.get("spheres_um", spheres)
            written.append(path)
            if progress is not None:
                progress(i, len(specs), spec, report)
            status = report.final.get("status")
            if report.exit_status not in ("done", "failed") or status not in spec.ends:
                raise ExperimentError(f"{path.name}: {spec.task} ended {report.exit_status} ({status}): "
                                      f"{report.reason}; the experiment stopped after run {i} of {len(specs)}")
    finally:
        handle.close()
    return written
