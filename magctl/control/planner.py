"""Wavefront path planner (paper §II, ref [22]) and the block that feeds its waypoints to the servo.

The workspace rectangle is cut into square cells of side ``h``. Obstacles
are the spheres inflated by the keep-out radius ``r_k`` (650 µm while the
robot repositions, paper §VI-B), each grown by half a cell diagonal so that
the straight segment between two free neighbouring cells stays out of every
inflated disc. A breadth-first wave from the goal numbers each free cell with
its 8-connected step count; the path descends the numbers from the start and is
then shortened by keeping only the waypoints needed for straight segments that
clear every disc of radius ``r_k`` (exact segment–circle test).

A start inside a keep-out disc first escapes radially to its edge (the
robot has just pushed the sphere); a goal inside one, outside the workspace or
cut off from the start raises :class:`PlanningError`.

The defaults are read from ``models/push.toml`` by :func:`planner_defaults`: the keep-out is ``[common]
clearance_um``, the cell side and the :class:`Planner` block's tolerances are ``[planner]``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import shortest_path

from magctl import FRAME_PERIOD_S
from magctl.config import load_model
from magctl.core.block import Block, StateVar
from magctl.core.errors import MagctlError
from magctl.core.ports import DIMENSIONLESS, Port
from magctl.core.units import UM_PER_M

_NEIGHBOURS = [(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)]


class PlanningError(MagctlError):
    """No path: the goal is blocked, outside the workspace or unreachable."""


@dataclass(frozen=True)
class PlannerDefaults:
    """The planner's defaults (m), from ``models/push.toml``: :func:`planner_defaults`."""

    keep_out: float
    """Keep-out distance from a sphere centre while repositioning: ``[common] clearance_um``
    (650 µm, paper §VI-B)."""
    cell: float
    """Grid cell side: ``[planner] cell_um``."""
    waypoint_tol: float
    """The :class:`Planner` block moves on to the next waypoint within this: ``[planner] waypoint_tol_um``."""
    replan_tol: float
    """The :class:`Planner` block plans again when a sphere has moved more than this:
    ``[planner] replan_tol_um``."""


def planner_defaults() -> PlannerDefaults:
    """The keep-out, cell side and block tolerances of ``models/push.toml`` (read on each call).

    The keep-out is the loaded SI value of ``[common] clearance_um``, the same number as
    :class:`~magctl.control.push_params.PlannedParams` ``clearance``. The ``[planner]`` values are the file's µm
    divided by :data:`~magctl.core.units.UM_PER_M`, the double nearest the length (``25 / 1e6 == 25e-6``): the
    loader's ``25 * 1e-6`` is one bit below it, and the grid's cell count ``floor((xmax − xmin) / h)`` can turn on
    that bit.
    """
    push = load_model("push")
    raw = push.planner.raw
    return PlannerDefaults(keep_out=float(push.common.clearance), cell=raw["cell_um"] / UM_PER_M,
                           waypoint_tol=raw["waypoint_tol_um"] / UM_PER_M, replan_tol=raw["replan_tol_um"] / UM_PER_M)


def segment_clearance(p0: np.ndarray, p1: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Smallest distance from each centre (N, 2) to the segment ``p0 → p1``."""
    d = p1 - p0
    L2 = float(d @ d)
    if L2 == 0.0:
        return np.linalg.norm(centres - p0, axis=1)
    t = np.clip((centres - p0) @ d / L2, 0.0, 1.0)
    return np.linalg.norm(centres - (p0 + t[:, None] * d), axis=1)


class Grid:
    """Cell geometry of the workspace ``bounds = (xmin, ymin, xmax, ymax)`` with cell side ``h``."""

    def __init__(self, bounds, h: float):
        self.x0, self.y0, self.x1, self.y1 = (float(b) for b in bounds)
        if not (self.x1 > self.x0 and self.y1 > self.y0) or h <= 0:
            raise PlanningError(f"workspace bounds {bounds} must have xmax > xmin, ymax > ymin and cell size > 0")
        self.h = float(h)
        self.nx = int(np.floor((self.x1 - self.x0) / h)) + 1
        self.ny = int(np.floor((self.y1 - self.y0) / h)) + 1

    def centre(self, cell) -> np.ndarray:
        return np.array([self.x0 + cell[1] * self.h, self.y0 + cell[0] * self.h])

    def cell(self, p) -> tuple[int, int]:
        return (int(np.clip(np.round((p[1] - self.y0) / self.h), 0, self.ny - 1)),
                int(np.clip(np.round((p[0] - self.x0) / self.h), 0, self.nx - 1)))

    def inside(self, p) -> bool:
        return self.x0 <= p[0] <= self.x1 and self.y0 <= p[1] <= self.y1

    def free_mask(self, centres: np.ndarray, keep_out: float) -> np.ndarray:
        yy, xx = np.mgrid[0:self.ny, 0:self.nx]
        x, y = self.x0 + xx * self.h, self.y0 + yy * self.h
        free = np.ones((self.ny, self.nx), dtype=bool)
        grow = keep_out + self.h * np.sqrt(0.5)
        for cx, cy in centres:
            free &= (x - cx) ** 2 + (y - cy) ** 2 >= grow**2
        return free


def wavefront(free: np.ndarray, goal: tuple[int, int]) -> np.ndarray:
    """8-connected breadth-first step count from ``goal`` to every free cell; −1 where unreachable.

    The free cells and their 8-neighbour links form an unweighted graph; scipy's breadth-first search over it
    (``shortest_path(unweighted=True)``) gives the wave's step counts.
    """
    dist = np.full(free.shape, -1, dtype=int)
    if not free[goal]:
        return dist
    ny, nx = free.shape
    idx = np.arange(free.size).reshape(free.shape)
    src, dst = [], []
    for di, dj in ((0, 1), (1, 0), (1, 1), (1, -1)):   # each undirected link once
        j0, j1 = max(0, -dj), nx - max(0, dj)
        a, b = (slice(0, ny - di), slice(j0, j1)), (slice(di, ny), slice(j0 + dj, j1 + dj))
        both = free[a] & free[b]
        src.append(idx[a][both])
        dst.append(idx[b][both])
    src, dst = np.concatenate(src), np.concatenate(dst)
    graph = csr_matrix((np.ones(src.size), (src, dst)), shape=(free.size, free.size))
    hops = shortest_path(graph, directed=False, unweighted=True, indices=int(idx[goal]))
    reach = np.isfinite(hops).reshape(free.shape)
    dist[reach] = hops.reshape(free.shape)[reach].astype(int)
    return dist


def _descend(dist: np.ndarray, start: tuple[int, int], goal_xy: np.ndarray, grid: Grid) -> list[tuple[int, int]]:
    cells = [start]
    c = start
    while dist[c] > 0:
        best, key = None, None
        for di, dj in _NEIGHBOURS:
            n = (c[0] + di, c[1] + dj)
            if 0 <= n[0] < dist.shape[0] and 0 <= n[1] < dist.shape[1] and dist[n] >= 0:
                k = (dist[n], float(np.linalg.norm(grid.centre(n) - goal_xy)))
                if key is None or k < key:
                    best, key = n, k
        c = best
        cells.append(c)
    return cells


def _shorten(points: np.ndarray, centres: np.ndarray, keep_out: float) -> np.ndarray:
    """Greedy line-of-sight shortening: from each kept point jump to the farthest visible one."""
    out = [points[0]]
    i = 0
    while i < len(points) - 1:
        j = len(points) - 1
        while j > i + 1 and len(centres) and segment_clearance(points[i], points[j], centres).min() < keep_out:
            j -= 1
        out.append(points[j])
        i = j
    return np.asarray(out)


def _attach(grid: Grid, free: np.ndarray, p: np.ndarray, centres: np.ndarray, keep_out: float):
    """The nearest free cell (within 3 cells) joined to ``p`` by a segment clear of every keep-out disc."""
    c0 = grid.cell(p)
    best, best_d = None, np.inf
    for di in range(-3, 4):
        for dj in range(-3, 4):
            c = (c0[0] + di, c0[1] + dj)
            if not (0 <= c[0] < grid.ny and 0 <= c[1] < grid.nx) or not free[c]:
                continue
            q = grid.centre(c)
            d = float(np.linalg.norm(q - p))
            if d < best_d and (not len(centres) or segment_clearance(p, q, centres).min() >= keep_out):
                best, best_d = c, d
    return best


def plan_path(start, goal, spheres, *, bounds, keep_out: float | None = None, cell: float | None = None) -> np.ndarray:
    """Waypoints (K, 2) in m from ``start`` to ``goal`` around the inflated spheres.

    Parameters
    ----------
    start, goal : (2,) array, m
    spheres : (N, 2) array, m
        Sphere centres; each is a disc of radius ``keep_out`` the path must not enter.
    bounds : (xmin, ymin, xmax, ymax), m
        Workspace rectangle.
    keep_out : float, optional
        Keep-out radius (m); default :func:`planner_defaults` ``keep_out``, 650 µm while repositioning (paper §VI-B).
    cell : float, optional
        Grid cell side (m); default :func:`planner_defaults` ``cell``, 25 µm.

    Raises
    ------
    PlanningError
        Goal outside the workspace, inside a keep-out disc, or unreachable.
    """
    if keep_out is None or cell is None:
        defaults = planner_defaults()
        keep_out = defaults.keep_out if keep_out is None else keep_out
        cell = defaults.cell if cell is None else cell
    start, goal = np.asarray(start, dtype=float), np.asarray(goal, dtype=float)
    centres = np.asarray(spheres, dtype=float).reshape(-1, 2)
    grid = Grid(bounds, cell)
    for label, p in (("start", start), ("goal", goal)):
        if not np.all(np.isfinite(p)) or not grid.inside(p):
            raise PlanningError(f"{label} {np.round(p * 1e6, 1).tolist()} µm is outside the workspace "
                                f"{np.round(np.array(bounds) * 1e6, 1).tolist()} µm")
    if len(centres):
        gap = np.linalg.norm(centres - goal, axis=1)
        if gap.min() < keep_out:
            i = int(np.argmin(gap))
            raise PlanningError(f"goal {np.round(goal * 1e6, 1).tolist()} µm is {gap[i] * 1e6:.0f} µm from sphere {i}, "
                                f"inside its {keep_out * 1e6:.0f} µm keep-out")
    head = [start]
    if len(centres):
        gap = np.linalg.norm(centres - start, axis=1)
        inside = gap < keep_out
        if inside.any():
            i = int(np.argmin(gap))
            away = start - centres[i]
            n = np.linalg.norm(away)
            away = away / n if n > 0 else (goal - centres[i]) / max(np.linalg.norm(goal - centres[i]), 1e-12)
            escape = centres[i] + away * (keep_out + grid.h)
            head.append(escape)
            start = escape
    free = grid.free_mask(centres, keep_out)
    gcell, scell = _attach(grid, free, goal, centres, keep_out), _attach(grid, free, start, centres, keep_out)
    if gcell is None:
        raise PlanningError(f"goal {np.round(goal * 1e6, 1).tolist()} µm is too close to a sphere for the "
                            f"{cell * 1e6:.0f} µm grid")
    dist = wavefront(free, gcell)
    if scell is None or dist[scell] < 0:
        raise PlanningError(f"goal {np.round(goal * 1e6, 1).tolist()} µm is unreachable from "
                            f"{np.round(start * 1e6, 1).tolist()} µm: the keep-out discs "
                            f"({keep_out * 1e6:.0f} µm) and the workspace bounds cut it off")
    cells = _descend(dist, scell, goal, grid)
    pts = np.array([start] + [grid.centre(c) for c in cells] + [goal])
    pts = _shorten(pts, centres, keep_out)
    return np.vstack([np.asarray(head[:-1]).reshape(-1, 2), pts]) if len(head) > 1 else pts


class Planner(Block):
    """Wavefront planner block: feeds the servo the next waypoint towards ``goal``.

    It plans when the goal changes or a sphere has moved more than ``replan_tol``
    since the last plan, and advances to the next waypoint once the robot is within
    ``waypoint_tol`` of the current one. Planning runs per trial (grid BFS); advancing
    is vectorised over the batch. ``keep_out``, ``cell``, ``waypoint_tol`` and ``replan_tol`` left ``None``
    take :func:`planner_defaults` (``models/push.toml``).

    Ports
    -----
    inputs: ``goal`` (2,) m, ``robot_est`` (2,) m, ``spheres_est`` (N, 2) m
    outputs: ``target`` (2,) m, ``final`` () bool (the target is the goal), ``feasible`` () bool,
    ``replans`` () count
    """

    def __init__(self, name: str = "planner", *, n_spheres: int = 1, bounds, keep_out: float | None = None,
                 cell: float | None = None, waypoint_tol: float | None = None, replan_tol: float | None = None,
                 max_waypoints: int = 64, dt: float = FRAME_PERIOD_S):
        defaults = planner_defaults()
        keep_out = defaults.keep_out if keep_out is None else keep_out
        cell = defaults.cell if cell is None else cell
        waypoint_tol = defaults.waypoint_tol if waypoint_tol is None else waypoint_tol
        replan_tol = defaults.replan_tol if replan_tol is None else replan_tol
        self.bounds = tuple(float(b) for b in bounds)
        Grid(self.bounds, cell)  # validates
        self.keep_out, self.cell = float(keep_out), float(cell)
        self.waypoint_tol, self.replan_tol = float(waypoint_tol), float(replan_tol)
        self.kmax = int(max_waypoints)
        n = int(n_spheres)
        super().__init__(name, inputs=[Port("goal", (2,), "m"), Port("robot_est", (2,), "m"),
                                       Port("spheres_est", (n, 2), "m")],
                         outputs=[Port("target", (2,), "m"), Port("final", (), DIMENSIONLESS, "bool"),
                                  Port("feasible", (), DIMENSIONLESS, "bool"), Port("replans", (), DIMENSIONLESS)],
                         dt=dt, feedthrough=True)

    def state_vars(self):
        n = self.inputs["spheres_est"].shape[0]
        return (StateVar("path", (self.kmax, 2), symbol="w", description="waypoints of the current plan, m"),
                StateVar("len", (), "int64", description="number of waypoints in the plan"),
                StateVar("idx", (), "int64", description="index of the current waypoint"),
                StateVar("goal", (2,), symbol="P_g", description="goal the plan was made for, m"),
                StateVar("spheres", (n, 2), symbol="P_s", description="sphere positions the plan was made for, m"),
                StateVar("feasible", (), "bool", description="the last plan reached the goal"),
                StateVar("replans", (), symbol="n_r", description="plans made so far"))

    def initial_state(self, batch, rng=None):
        n = self.inputs["spheres_est"].shape[0]
        return {"path": np.zeros((batch, self.kmax, 2)), "len": np.zeros(batch, dtype=np.int64),
                "idx": np.zeros(batch, dtype=np.int64), "goal": np.full((batch, 2), np.nan),
                "spheres": np.full((batch, n, 2), np.nan), "feasible": np.ones(batch, dtype=bool),
                "replans": np.zeros(batch)}

    def _plan(self, state, u):
        path, length, idx = state["path"].copy(), state["len"].copy(), state["idx"].copy()
        feasible, replans = state["feasible"].copy(), state["replans"].copy()
        goal, sph, robot = u["goal"], u["spheres_est"], u["robot_est"]
        moved = np.abs(sph - state["spheres"]).reshape(len(goal), -1)
        need = (length == 0) | np.any(goal != state["goal"], axis=1) | np.any(~(moved <= self.replan_tol), axis=1)
        for b in np.flatnonzero(need):
            try:
                wp = plan_path(robot[b], goal[b], sph[b], bounds=self.bounds, keep_out=self.keep_out, cell=self.cell)
                feasible[b] = True
            except PlanningError:
                wp = robot[b][None]
                feasible[b] = False
            wp = wp[1:] if len(wp) > 1 else wp  # the first point is where the robot is
            if len(wp) > self.kmax:
                wp = np.vstack([wp[: self.kmax - 1], wp[-1:]])
            path[b, : len(wp)] = wp
            length[b], idx[b] = len(wp), 0
            replans[b] += 1
        # advance past reached waypoints (vectorised)
        rows = np.arange(len(goal))
        near = np.linalg.norm(path[rows, idx] - robot, axis=1) < self.waypoint_tol
        step = near & (idx < length - 1)
        idx = idx + step
        return path, length, idx, feasible, replans, need

    def step(self, state, u):
        """Plan (where needed) once per frame: the target now and the plan kept for the next frame."""
        path, length, idx, feasible, replans, need = self._plan(state, u)
        rows = np.arange(len(idx))
        out = {"target": path[rows, idx].copy(), "final": idx >= length - 1, "feasible": feasible.copy(),
               "replans": replans.copy()}
        return out, {"path": path, "len": length, "idx": idx, "feasible": feasible, "replans": replans,
                     "goal": np.where(need[:, None], u["goal"], state["goal"]),
                     "spheres": np.where(need[:, None, None], u["spheres_est"], state["spheres"])}

    def output(self, state, u):
        return self.step(state, u)[0]

    def update(self, state, u):
        return self.step(state, u)[1]
