"""Multi-sphere assembly by planned passes (docs/push-control.md §8) as a batched state machine at 30 Hz.

One attempt, per trial:

1. the :class:`~magctl.control.assembly_planner.PassPlanner` block turns the tracked spheres into the next
   pass ``a → b`` (optimised on the pass map, or the greedy baseline);
2. ``REPOSITION`` — the robot travels to ``a`` along the paper's wavefront path (§II,
   :func:`magctl.control.planner.plan_path`) round every sphere at the repositioning keep-out;
3. ``PASS`` — it drives the pass at the pushing speed;
4. ``SETTLE`` — it waits, then the spheres are measured: the arrangement assembled
   (:meth:`~magctl.control.arrangement.Arrangement.assembled`, eq 21 on every contact) ends the task,
   otherwise the planner learns from the pass and plans the next.

The frames are compiled (:func:`magctl.control.push.planned_kernel.planned_frame`); the plan
is the block's Python event (:meth:`PlannedAssemblyTask.handle_event`, docs/core.md "Python events"): the frame
that needs a pass raises ``plan_due``, the planner runs at the end of that frame for those trials only, and the pass
and its path apply from ``plan_frames`` frames after it on (1: the next frame); the robot is held in between.

On a rig the planner runs off the tick (docs/rig.md "Planning off the frame"): the flag stays up while a worker
plans, and every frame that starts with it up holds the robot — speed cap 0 (no oscillating field), the target
kept, the rest of the state as it was — until the result is merged; a frame in the ``plan_frames`` wait holds the
same way. So a study, a lock-step rig run and a real-time run whose plan was ready within ``plan_frames`` frames
make the same frames (``benchmarks/bench_planning_off_frame.py`` times the plan).

A trial for which the planner finds no pass that keeps its bounds ends ``STALLED``.
"""

from __future__ import annotations

import numpy as np

from magctl import FRAME_PERIOD_S
from magctl.config import load_model
from magctl.control.arrangement import arrangement as make_arrangement
from magctl.control.assembly_planner import PassPlanner, PlanLimits
from magctl.control.phases import FINISHED, START, SidePhase
from magctl.control.planner import PlanningError, plan_path, planner_defaults
from magctl.control.push.common import PushTask
from magctl.control.push_params import PlannedParams
from magctl.control.status import Status
from magctl.core.block import Block, StateVar
from magctl.core.errors import MagctlError
from magctl.core.ports import Port

REPOSITION, PASS, SETTLE = int(SidePhase.REPOSITION), int(SidePhase.PASS), int(SidePhase.SETTLE)
MAX_WAYPOINTS = 24
"""Waypoints kept for one repositioning path (the wavefront path after shortening has a handful)."""
PLAN_FRAMES = 1
"""Frames from the frame that requests a plan to the first that uses it (``plan_frames``): 1, the next frame."""


class PlannedAssemblyTask(PushTask, Block):
    """Assembly of ``n_spheres`` spheres into ``arrangement`` by passes the planner chooses.

    Parameters
    ----------
    n_spheres : int
        Spheres on the slide, all of them in the arrangement (2, 3 or 4).
    arrangement : {"pair", "line", "triangle"}
        The target (:data:`~magctl.control.arrangement.ARRANGEMENTS`); default: a pair for 2, a line otherwise.
    planner : {"optimal", "greedy"}
        Passes optimised on the pass map with IPOPT, or the paper's method one sphere at a time
        (:data:`~magctl.control.assembly_planner.PLANNERS`).
    params : PlannedParams, optional
        The task's parameters (:class:`~magctl.control.push_params.PlannedParams`); by default the file's.
    **overrides
        Any field of the record (``None`` keeps the value): ``eps_as`` (``ε_as`` of eq 21, ``[assembly]``),
        ``max_attempts`` (passes before the task gives up, ``[plan] max_passes``), ``clearance`` (the
        repositioning keep-out, ``[plan]``), ``pass_speed`` (``[side]``) and the shared ``arrive_tol``,
        ``travel_speed``, ``settle_frames``, ``max_lost_frames``, ``phase_timeout_frames``, ``workspace``.
    plan_frames : int, optional
        Frames from the frame that requests a plan to the first frame that uses it (default :data:`PLAN_FRAMES`,
        1: the next one); the robot is held in between. The planning budget of a rig that plans off the tick
        (docs/rig.md "Planning off the frame"): a plan ready in time gives the rig the frames of a study.

    Ports: inputs as every push task; outputs as every push task plus ``gap`` (m), the smallest distance of
    the pass from a sphere, measured when it is planned; ``correction`` is the planner's predicted RMS bond
    error after the pass (both 0 until the first pass is planned).
    """

    PHASES = {START: "start", REPOSITION: "reposition", PASS: "pass", SETTLE: "settle", FINISHED: "finished"}

    PARAMS = PlannedParams

    def __init__(self, name: str = "planned_assembly", *, n_spheres: int = 3, arrangement: str | None = None,
                 planner: str = "optimal", params: PlannedParams | None = None, plan_frames: int | None = None,
                 **overrides):
        n_spheres = int(n_spheres)
        what = f"assembly {name!r}"
        if not 2 <= n_spheres <= 4:
            raise MagctlError(f"{what}: n_spheres={n_spheres} must be 2, 3 or 4")
        plan_frames = PLAN_FRAMES if plan_frames is None else plan_frames
        if isinstance(plan_frames, bool) or int(plan_frames) != plan_frames or plan_frames < 1:
            raise MagctlError(f"{what}: plan_frames={plan_frames!r} must be a whole number of frames >= 1")
        self.plan_frames = int(plan_frames)
        self._check_common(what, params, overrides, goal=(0.0, 0.0), n_spheres=n_spheres, sphere=0)
        self.target = make_arrangement(arrangement or ("pair" if n_spheres == 2 else "line"), n_spheres,
                                       eps_as=self.eps_as)
        self.sphere_indices = tuple(range(n_spheres))
        self.law = PassPlanner(self.target, f"{name}_planner", planner=planner)
        self.cell = float(load_model("push").plan.reposition_cell)
        planner = planner_defaults()
        self.planner_keep_out = planner.keep_out   # the paper's 650 µm, [common] clearance_um
        # the robot counts as past an intermediate waypoint within this ([planner] waypoint_tol_um; the pass start
        # needs arrive_tol)
        self.waypoint_tol = planner.waypoint_tol
        self.law_limits = PlanLimits.default()
        self.bounds = self.law_limits.field
        ins, outs = self._ports(n_spheres)
        outs.append(Port("gap", (), "m"))
        Block.__init__(self, name, inputs=ins, outputs=outs, dt=FRAME_PERIOD_S, feedthrough=True)

    def state_vars(self):
        return (*self._common_vars(),
                StateVar("waypoints", (MAX_WAYPOINTS, 2), description="repositioning path to the pass start, m"),
                StateVar("n_waypoints", (), "int64", description="waypoints in the path"),
                StateVar("waypoint", (), "int64", description="index of the waypoint the robot heads for"),
                StateVar("start", (2,), symbol="a", description="start of the pass, m"),
                StateVar("end", (2,), symbol="b", description="end of the pass, m"),
                StateVar("gap", (), description="closest approach of the pass to a sphere, m"),
                StateVar("plan_due", (), "bool", description="the next pass is to be planned (the Python event)"),
                StateVar("plan_wait", (), "int64", description="frames the robot is still held for the plan"))

    def initial_state(self, batch, rng=None):
        st = self._common_state(batch)
        st |= {"waypoints": np.full((batch, MAX_WAYPOINTS, 2), np.nan),
               "n_waypoints": np.zeros(batch, dtype=np.int64), "waypoint": np.zeros(batch, dtype=np.int64),
               "start": np.full((batch, 2), np.nan), "end": np.full((batch, 2), np.nan),
               "gap": np.full(batch, np.nan), "plan_due": np.zeros(batch, dtype=bool),
               "plan_wait": np.zeros(batch, dtype=np.int64)}
        return st

    def kernel(self):
        """The compiled frame (:func:`~magctl.control.push.planned_kernel.planned_frame`); the plan is its Python
        event."""
        from magctl.control.push.planned_kernel import planned_frame
        from magctl.core.kernel import Kernel

        x0, y0, x1, y1 = self.bounds
        pad = self.workspace
        area = np.array([x0 - pad, y0 - pad, x1 + pad, y1 + pad])
        shape = np.array([self.target.eps_as, np.cos(self.target.bend / 2)])
        return Kernel(step=planned_frame, event="plan_due",
                      params=(self.params.packed(), area, self.target.bonds, self.target.contact.copy(), shape,
                              self.waypoint_tol, self.plan_frames))

    def handle_event(self, state, u):
        """Plan the next pass (the :class:`~magctl.control.assembly_planner.PassPlanner` block: IPOPT on the pass
        map, or the greedy baseline) and the wavefront path to its start, for the trials whose frame raised
        ``plan_due``; a trial with no feasible pass ends ``STALLED``. Runs after the frame that ended the last
        pass (or the first frame), on that frame's measurements — or, on a rig, in a worker while the frames go
        on holding the robot (docs/rig.md "Planning off the frame")."""
        r = np.asarray(u["robot_est"], dtype=float)
        spheres = np.asarray(u["spheres_est"], dtype=float)
        new = {k: (v.copy() if isinstance(v, np.ndarray) else v) for k, v in state.items()}
        due = np.asarray(state["plan_due"], dtype=bool)
        new["law"] = self.law.update_where(state["law"], {"spheres": spheres, "robot": r}, due)
        a, b = new["law"]["start"], new["law"]["end"]
        none = due & ~np.isfinite(a).all(axis=1)
        new["status"] = np.where(none, Status.STALLED, new["status"])
        new["phase"] = np.where(none, FINISHED, new["phase"])
        new["target"] = np.where(none[:, None], r, new["target"])
        go = due & ~none
        for k in np.flatnonzero(go):
            path = self._reposition_path(r[k], a[k], spheres[k])
            if len(path) > MAX_WAYPOINTS:   # not expected after shortening; keep the way out and the pass start
                path = np.concatenate([path[: MAX_WAYPOINTS - 1], path[-1:]])
            new["waypoints"][k] = np.nan
            new["waypoints"][k, : len(path)] = path
            new["n_waypoints"][k] = len(path)
            new["waypoint"][k] = 0
            d = b[k] - a[k]
            t = np.clip((spheres[k] - a[k]) @ d / (d @ d), 0.0, 1.0)
            new["gap"][k] = float(np.min(np.linalg.norm(spheres[k] - (a[k] + t[:, None] * d), axis=1)))
        new["start"] = np.where(go[:, None], a, new["start"])
        new["end"] = np.where(go[:, None], b, new["end"])
        new["phase"] = np.where(go, REPOSITION, new["phase"])
        new["frames"] = np.where(go, 0, new["frames"])
        new["plan_due"] = np.zeros_like(due)
        return new

    def _reposition_path(self, robot, start, spheres) -> np.ndarray:
        """Waypoints to the pass start round every sphere (the robot's own position dropped).

        The keep-out is the repositioning clearance; where the spheres, moved by the last pass, close every
        way round at it, the paper's 650 µm (§VI, if smaller) and then the planner's pass gap are tried before
        a straight line (the pass start itself keeps the clearance when it is planned).
        """
        x0, y0, x1, y1 = self.bounds
        pad = 2 * self.cell   # the pass ends may lie on the field's edge: the grid reaches past it
        bounds = (x0 - pad, y0 - pad, x1 + pad, y1 + pad)
        keep_outs = dict.fromkeys((self.clearance, min(self.clearance, self.planner_keep_out), self.law_limits.min_gap))
        for keep_out in keep_outs:
            try:
                path = plan_path(robot, start, spheres, bounds=bounds, keep_out=keep_out, cell=self.cell)
                return path[1:] if len(path) > 1 else path
            except PlanningError:
                continue
        return np.asarray([start])


__all__ = ["PlannedAssemblyTask"]
