"""The paper's two simulated experiments (§IV-D) and the inverse-model numbers controllers need.

* side-push (Fig 6): the robot passes a sphere at a side gap D_g; the sphere is
  displaced D_s. :func:`sidepush_curve`, :func:`sidepush_fit` (eq 22 form
  ``D_s = a exp(-b D_g)``), :func:`contact_threshold`, :func:`gap_for_displacement`.
* release (§IV-D): the sphere starts against the robot's concave front face and
  the robot backs away; the sphere follows a distance D_p,r.
  :func:`release_displacement`.

Gaps D_g are measured from the robot's centre line to the sphere centre (Fig 2).
All functions take lengths in metres and return metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

ROBOT_SPEED = 0.4e-3
"""Robot speed [m/s] (paper §IV-C: 0.4 mm/s, the average experimental speed)."""

APPROACH = 1.0e-3
"""Start and end distance of the robot from the sphere along its path [m] (paper §VI: 1 mm)."""


def _spheres(initial, **kw):
    from magctl.plant.sphere import Spheres

    return Spheres(initial, **kw)


def _run(block, batch, positions, heading, velocity):
    """Step ``block`` through robot positions ``(T, B, 2)``; return sphere paths ``(T+1, B, N, 2)`` and contact."""
    state = block.initial_state(batch)
    out = [state["xy"].copy()]
    contact = np.zeros(batch, bool)
    hd = np.broadcast_to(heading, (batch,)).astype(float)
    for p, v in zip(positions, velocity, strict=True):
        state = block.update(state, {"position": p, "heading": hd, "velocity": v})
        contact |= state["contact"]
        out.append(state["xy"].copy())
    return np.asarray(out), contact


def _drive_past(gaps: np.ndarray, reach: float, speed: float, block_kw: dict):
    """The robot drives along +x from ``-reach`` to ``+reach`` at ``speed`` past one sphere per trial at
    ``(0, D_g)``: robot positions ``(T,)``, the step, sphere paths ``(T+1, G, 1, 2)`` and contact ``(G,)``."""
    b = len(gaps)
    init = np.zeros((b, 1, 2))
    init[:, 0, 1] = gaps
    block = _spheres(init, **block_kw)
    step = speed * block.dt
    n = int(np.ceil(2 * reach / step))
    x = -reach + step * np.arange(n)
    pos = np.zeros((n, b, 2))
    pos[:, :, 0] = x[:, None]
    vel = np.zeros((n, b, 2))
    vel[:, :, 0] = speed
    path, contact = _run(block, b, pos, 0.0, vel)
    return x, step, path, contact


@dataclass
class SidePushResult:
    """Sphere displacement for each side gap.

    Attributes
    ----------
    gaps : ndarray (G,)
        D_g [m].
    displacement : ndarray (G,)
        D_s [m], the sphere's net displacement.
    along : ndarray (G,)
        Component of D_s along the robot's motion [m].
    across : ndarray (G,)
        Component of D_s away from the robot's line [m] (negative: pulled towards it).
    contact : ndarray (G,) bool
        Whether the robot touched the sphere.
    """

    gaps: np.ndarray
    displacement: np.ndarray
    along: np.ndarray
    across: np.ndarray
    contact: np.ndarray


def sidepush_curve(gaps, speed: float = ROBOT_SPEED, travel: float = APPROACH, **block_kw) -> SidePushResult:
    """Fig 6: the robot drives along +x past a sphere at ``(0, D_g)``, from ``-travel`` to ``+travel``.

    Extra keywords go to :class:`magctl.plant.sphere.Spheres` (``drag_mode``, ``roughness``, ``geometry``,
    ``domain`` — a :class:`magctl.plant.fluid.domain.Domain` for a bounded oil layer —, or ``flow``, which
    replaces the robot's flow, e.g. by the box model's :class:`~magctl.plant.fluid.fem_box.BoxFlow`).
    """
    gaps = np.atleast_1d(np.asarray(gaps, float))
    if np.any(gaps <= 0):
        raise ValueError("side gaps D_g must be positive")
    if speed <= 0 or travel <= 0:
        raise ValueError("speed and travel must be positive")
    _x, _step, path, contact = _drive_past(gaps, travel, speed, block_kw)
    d = path[-1, :, 0] - path[0, :, 0]
    return SidePushResult(gaps, np.linalg.norm(d, axis=-1), d[:, 0], d[:, 1], contact)


@dataclass
class PassProfile:
    """A sphere's displacement while the robot passes it, as a function of the robot's position.

    Attributes
    ----------
    positions : ndarray (T,)
        The robot's position ``x`` along its line, relative to the sphere's start [m].
    gaps : ndarray (G,)
        Side gaps ``D_g`` from the robot's line to the sphere centre [m].
    along, away : ndarray (T, G)
        The sphere's displacement since the robot was at ``positions[0]``, along the robot's motion and away
        from its line [m].
    contact : ndarray (G,) bool
        Whether the robot touched the sphere.
    """

    positions: np.ndarray
    gaps: np.ndarray
    along: np.ndarray
    away: np.ndarray
    contact: np.ndarray


def pass_profile(gaps, reach: float = 3e-3, speed: float = ROBOT_SPEED, **block_kw) -> PassProfile:
    """The robot drives along +x from ``-reach`` to ``+reach`` past a sphere at ``(0, D_g)``; the sphere's
    displacement after every frame (the cumulative form of Fig 6 that a pass of any start and end reads from).

    A pass from ``x0`` to ``x1`` (robot positions relative to the sphere) moves it by about
    ``profile(x1) − profile(x0)``: exactly so where the sphere's own motion during the pass leaves the flow
    it sees unchanged (``D_s`` ≪ the flow's decay length, here ~ 70 µm against ≥ 370 µm). Keywords go to
    :class:`magctl.plant.sphere.Spheres` as in :func:`sidepush_curve`.
    """
    gaps = np.atleast_1d(np.asarray(gaps, float))
    if np.any(gaps < 0):
        raise ValueError("side gaps D_g must be non-negative")
    if speed <= 0 or reach <= 0:
        raise ValueError("speed and reach must be positive")
    x, step, path, contact = _drive_past(gaps, reach, speed, block_kw)
    d = path[1:, :, 0] - path[0, :, 0]
    return PassProfile(x + step, gaps, d[..., 0], d[..., 1], contact)


def sidepush_fit(gaps, displacement):
    """Least-squares fit of eq 22's form ``D_s = a exp(-b D_g)`` (in log space).

    Returns ``(a [m], b [1/m], r2)``; r² is computed on D_s itself.
    """
    g = np.asarray(gaps, float)
    d = np.asarray(displacement, float)
    ok = d > 0
    if ok.sum() < 2:
        raise ValueError("need at least two positive displacements to fit D_s = a exp(-b D_g)")
    slope, icpt = np.polyfit(g[ok], np.log(d[ok]), 1)
    a, bb = float(np.exp(icpt)), float(-slope)
    pred = a * np.exp(-bb * g[ok])
    r2 = 1.0 - np.sum((d[ok] - pred) ** 2) / np.sum((d[ok] - d[ok].mean()) ** 2)
    return a, bb, float(r2)


def gap_for_displacement(ds, a: float, b: float):
    """Inverse of the fit, eq 22: ``D_g = -ln(D_s / a) / b`` [m]."""
    ds = np.asarray(ds, float)
    if np.any(ds <= 0):
        raise ValueError("desired displacement D_s must be positive")
    return -np.log(ds / a) / b


def contact_threshold(lo: float = 200e-6, hi: float = 650e-6, tol: float = 2e-6, **block_kw) -> float:
    """Smallest side gap at which the passing robot does not touch the sphere [m] (Fig 6's division).

    Bisection on batched passes (8 gaps per round). Keywords go to :func:`sidepush_curve` and on to
    :class:`magctl.plant.sphere.Spheres` (``flow=`` among them).
    """
    while hi - lo > tol:
        g = np.linspace(lo, hi, 8)
        c = sidepush_curve(g, **block_kw).contact
        if c.all():
            return float(hi)
        if not c.any():
            return float(lo)
        k = int(np.nonzero(~c)[0][0])
        lo, hi = g[k - 1], g[k]
    return float(hi)


def release_displacement(retract: float = 1.5e-3, speed: float = ROBOT_SPEED, batch: int = 1,
                         seed: int | None = None, return_path: bool = False, **block_kw):
    """D_p,r: the sphere starts in the robot's concave front face; the robot backs away ``retract``.

    Returns the sphere's displacement along the retreat for each of ``batch`` trials [m]
    (``seed`` draws per-trial variability when the sphere model has any). With
    ``return_path`` also the robot's retreat ``(T,)`` and the sphere's displacement ``(T, B)``.
    """
    if retract <= 0 or speed <= 0:
        raise ValueError("retract distance and speed must be positive")
    from magctl.core.random import TrialStreams
    from magctl.plant.outline import polygon_distance

    probe = _spheres(np.zeros((1, 2)), **block_kw)
    foot = probe.footprint
    # sphere centre on the front axis where it just touches the concave face
    xs = np.linspace(0.0, foot[:, 0].max() + probe.radius, 4000)
    pts = np.column_stack([xs, np.zeros_like(xs)])
    dist, _ = polygon_distance(pts, foot)
    from magctl.plant.outline import points_in_polygon

    ok = (~points_in_polygon(pts, foot)) & (dist >= probe.radius)
    x0 = xs[np.argmax(ok)]
    init = np.array([[x0 + 1e-7, 0.0]])
    block = _spheres(init, **block_kw)
    rng = TrialStreams.for_block(seed, range(batch), block.name) if (seed is not None and block.uses_random) else None
    state = block.initial_state(batch, rng)
    step = speed * block.dt
    n = int(np.ceil(retract / step))
    start = state["xy"][:, 0, 0].copy()
    hd = np.zeros(batch)
    path = [np.zeros(batch)]
    for k in range(n):
        p = np.zeros((batch, 2))
        p[:, 0] = -k * step
        v = np.zeros((batch, 2))
        v[:, 0] = -speed
        state = block.update(state, {"position": p, "heading": hd, "velocity": v})
        path.append(start - state["xy"][:, 0, 0])
    if return_path:
        return path[-1], step * np.arange(n + 1), np.asarray(path)
    return path[-1]
