"""The Stokes flow of the translating robot above the glass, with cached maps in the robot frame.

The robot (geometry from :mod:`magctl.plant.fluid.geometry`) is a rigid body
near the no-slip glass. Its surface carries regularised Stokeslets with Blake's
wall images (:mod:`magctl.plant.fluid.stokes`); solving once for unit
translation along the body ``x`` and ``y`` axes gives two force sets, and by
Stokes linearity the flow of any in-plane velocity is their combination
(paper §III: position, not velocity, sets the displacement).

The flow at the sphere-centre height is sampled once on a grid in the robot
frame (both motions, three components), so a frame of a batched simulation is
a table look-up, a scaling by the body-frame velocity and a rotation. Maps are
cached by geometry, viscosity and height, so a changed parameter gives a new
solve and never a stale map.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.linalg

from magctl.plant.fluid.geometry import RobotGeometry
from magctl.plant.fluid.stokes import regularized_blake_tensor, regularized_blake_velocity

EPS_RATIO = 0.5
"""Regularisation blob size as a fraction of the surface spacing (Cortez et al. 2005 use ε ≈ spacing/2)."""


def _axis(half: float, fine_half: float, fine_step: float, growth: float = 1.25, start: float = 0.0) -> np.ndarray:
    """Non-negative grid nodes: ``fine_step`` up to ``fine_half``, then growing steps to ``half``."""
    nodes = list(np.arange(start, fine_half + fine_step / 2, fine_step))
    step = fine_step
    while nodes[-1] < half:
        step *= growth
        nodes.append(min(nodes[-1] + step, half))
    return np.asarray(nodes)


@dataclass
class RobotFlow:
    """Flow of the robot translating at unit speed along its body axes, and its grid maps.

    Attributes
    ----------
    geometry : RobotGeometry
    viscosity : float
        μ [Pa·s].
    height : float
        Height of the map plane above the glass [m] (the sphere centre, R + ε).
    points : ndarray (M, 3)
        Surface points carrying the Stokeslets (robot frame).
    forces : ndarray (2, M, 3)
        Stokeslet strengths for unit velocity along body x and body y [N per m/s].
    eps : float
        Regularisation length [m].
    gx, gy : ndarray
        Map grid nodes [m] (``gy`` symmetric about 0).
    maps : ndarray (2, ny, nx, 3)
        Flow [m/s per m/s] on the grid for each unit motion.
    inside : ndarray (ny, nx) bool
        Grid nodes inside the robot (flow there is the rigid velocity).
    """

    geometry: RobotGeometry
    viscosity: float
    height: float
    map_half: float = 1.5e-3
    map_step: float = 15e-6
    points: np.ndarray = field(init=False, repr=False)
    forces: np.ndarray = field(init=False, repr=False)
    eps: float = field(init=False)
    gx: np.ndarray = field(init=False, repr=False)
    gy: np.ndarray = field(init=False, repr=False)
    maps: np.ndarray = field(init=False, repr=False)
    inside: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        if self.viscosity <= 0:
            raise ValueError(f"viscosity must be positive, got {self.viscosity!r} Pa*s")
        if self.height <= 0:
            raise ValueError(f"map height must be above the glass, got {self.height!r} m")
        self._solve()
        self._build_maps()

    # --- the solve ---------------------------------------------------------------------
    def _solve(self) -> None:
        pts = self.geometry.collocation_points()
        self.eps = EPS_RATIO * self.geometry.spacing
        self.points = pts
        if self.geometry.is_symmetric():
            self.forces = self._solve_symmetric(pts, self.geometry.axis_count)
            return
        a = regularized_blake_tensor(pts, pts, self.eps).reshape(3 * len(pts), 3 * len(pts))
        a /= 8.0 * np.pi * self.viscosity
        rhs = np.zeros((3 * len(pts), 2))
        rhs[0::3, 0] = 1.0
        rhs[1::3, 1] = 1.0
        sol = scipy.linalg.solve(a, rhs, assume_a="gen")
        self.forces = sol.T.reshape(2, len(pts), 3)

    def _solve_symmetric(self, pts: np.ndarray, n0: int) -> np.ndarray:
        """Both unit motions using the robot's mirror symmetry about y = 0.

        Points are ``[axis (n0), upper (n1), mirrored upper (n1)]``. Motion along body x is even:
        a mirrored point carries ``(f_x, -f_y, f_z)`` of its partner and axis points have
        ``f_y = 0``; motion along body y is odd: ``(-f_x, f_y, -f_z)`` and axis points only ``f_y``.
        Imposing the boundary condition on the axis and upper points then fixes every point.
        """
        n1 = (len(pts) - n0) // 2
        rows = pts[: n0 + n1]
        g = regularized_blake_tensor(rows, pts, self.eps) / (8.0 * np.pi * self.viscosity)   # (R, 3, P, 3)
        forces = np.zeros((2, len(pts), 3))
        for k, (mirror, axis_comp) in enumerate((((1.0, -1.0, 1.0), [0, 2]), ((-1.0, 1.0, -1.0), [1]))):
            folded = g[:, :, n0:n0 + n1, :] + g[:, :, n0 + n1:, :] * np.asarray(mirror)
            cols = np.concatenate([g[:, :, :n0, axis_comp].reshape(len(rows), 3, -1),
                                   folded.reshape(len(rows), 3, -1)], axis=2)
            keep_rows = np.ones((len(rows), 3), bool)
            keep_rows[:n0] = False
            keep_rows[:n0, axis_comp] = True
            a = cols[keep_rows]
            rhs = np.zeros((len(rows), 3))
            rhs[:, k] = 1.0
            sol = scipy.linalg.solve(a, rhs[keep_rows], assume_a="gen")
            na = n0 * len(axis_comp)
            f_axis = np.zeros((n0, 3))
            f_axis[:, axis_comp] = sol[:na].reshape(n0, len(axis_comp))
            f_up = sol[na:].reshape(n1, 3)
            forces[k, :n0] = f_axis
            forces[k, n0:n0 + n1] = f_up
            forces[k, n0 + n1:] = f_up * np.asarray(mirror)
        return forces

    def velocity_exact(self, pts: np.ndarray) -> np.ndarray:
        """Flow ``(2, P, 3)`` at robot-frame points ``(P, 3)`` for unit body-x and body-y motion."""
        return regularized_blake_velocity(pts, self.points, self.forces, self.viscosity, self.eps)

    def drag(self) -> np.ndarray:
        """Hydrodynamic force on the robot ``(2, 3)`` [N per m/s] for the two unit motions."""
        return -self.forces.sum(axis=1)

    # --- the maps ------------------------------------------------------------------------
    def _build_maps(self) -> None:
        fine = 0.6e-3
        pos = _axis(self.map_half, fine, self.map_step)
        self.gx = np.concatenate([-pos[:0:-1], pos])
        self.gy = self.gx.copy()
        # mirror symmetry of the robot about its x-z plane: compute y >= 0 only
        ypos = pos
        xx, yy = np.meshgrid(self.gx, ypos)
        pts = np.column_stack([xx.ravel(), yy.ravel(), np.full(xx.size, self.height)])
        inside = self.geometry.contains(pts)
        u = np.zeros((2, len(pts), 3))
        u[:, ~inside] = self.velocity_exact(pts[~inside])
        u[0, inside] = (1.0, 0.0, 0.0)
        u[1, inside] = (0.0, 1.0, 0.0)
        half = u.reshape(2, len(ypos), len(self.gx), 3)
        # body-x motion is even in y for (u_x, u_z) and odd for u_y; body-y motion the reverse
        parity = np.array([[1.0, -1.0, 1.0], [-1.0, 1.0, -1.0]])
        lower = half[:, :0:-1] * parity[:, None, None, :]
        self.maps = np.concatenate([lower, half], axis=1)
        ins = inside.reshape(len(ypos), len(self.gx))
        self.inside = np.concatenate([ins[:0:-1], ins], axis=0)

    def _flat_maps(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Both maps as one ``(ny·nx, 6)`` table (x-motion flow, then y-motion flow) and the grid spacings."""
        flat = getattr(self, "_flat", None)
        if flat is None:
            m = self.maps
            flat = np.ascontiguousarray(m.transpose(1, 2, 0, 3).reshape(m.shape[1] * m.shape[2], 6))
            self._flat = flat = (flat, np.diff(self.gx), np.diff(self.gy))
        return flat

    @staticmethod
    def _corner_offsets(nx: int) -> np.ndarray:
        return np.array([0, 1, nx, nx + 1])

    def lookup(self, xy: np.ndarray, v_body: np.ndarray) -> np.ndarray:
        """Flow ``(..., 3)`` [m/s] at robot-frame plane points ``xy (..., 2)`` for body velocity ``(..., 2)``.

        Bilinear in the map; points beyond the map are summed directly (exact).
        """
        xy = np.asarray(xy, float)
        v_body = np.asarray(v_body, float)
        ux, uy, uz = self.lookup_components(xy[..., 0], xy[..., 1], v_body[..., 0], v_body[..., 1])
        return np.stack([ux, uy, uz], axis=-1)

    def lookup_components(self, x: np.ndarray, y: np.ndarray, vx: np.ndarray, vy: np.ndarray):
        """:meth:`lookup` on coordinate arrays: points ``(x, y)`` and body velocity ``(vx, vy)``, all of one
        shape (or broadcastable to the points'); returns the flow components ``(u_x, u_y, u_z)``."""
        flat, dgx, dgy = self._flat_maps()
        gx, gy = self.gx, self.gy
        nx = len(gx)
        # np.minimum/np.maximum and take: the same numbers as np.clip and fancy indexing, fewer layers
        ix = np.minimum(np.maximum(np.searchsorted(gx, x) - 1, 0), nx - 2)
        iy = np.minimum(np.maximum(np.searchsorted(gy, y) - 1, 0), len(gy) - 2)
        tx = (x - gx.take(ix)) / dgx.take(ix)
        ty = (y - gy.take(iy)) / dgy.take(iy)
        sx, sy = 1 - tx, 1 - ty
        # the four corners of every cell from one table, blended in the order w00, w01, w10, w11
        corners = flat.take((iy * nx + ix)[..., None] + self._corner_offsets(nx), axis=0)      # (..., 4, 6)
        w = np.stack([sx * sy, tx * sy, sx * ty, tx * ty], axis=-1)
        u = (w[..., None] * corners).sum(axis=-2)
        u = u[..., :3] * vx[..., None] + u[..., 3:] * vy[..., None]
        ux, uy, uz = u[..., 0], u[..., 1], u[..., 2]
        lim_x, lim_y = gx[-1], gy[-1]
        if np.abs(x).max(initial=0.0) > lim_x or np.abs(y).max(initial=0.0) > lim_y:
            outside = (np.abs(x) > lim_x) | (np.abs(y) > lim_y)
            vx, vy = np.broadcast_to(vx, x.shape), np.broadcast_to(vy, x.shape)
            pts = np.column_stack([x[outside], y[outside], np.full(int(outside.sum()), self.height)])
            far = self.velocity_exact(pts)
            vbx, vby = vx[outside][:, None], vy[outside][:, None]
            exact = vbx * far[0] + vby * far[1]
            ux, uy, uz = ux.copy(), uy.copy(), uz.copy()
            ux[outside], uy[outside], uz[outside] = exact[:, 0], exact[:, 1], exact[:, 2]
        return ux, uy, uz


_CACHE: dict[tuple, RobotFlow] = {}


def robot_flow(geometry: RobotGeometry | None = None, viscosity: float | None = None,
               height: float | None = None) -> RobotFlow:
    """The cached :class:`RobotFlow` for this geometry, viscosity and map height.

    Defaults come from ``models/robot_geometry.toml``, ``models/fluid.toml`` (μ = ν ρ) and
    ``models/sphere.toml`` (height R + ε). A new key (any changed parameter) solves anew.
    """
    from magctl.plant.fluid.params import fluid_viscosity, sphere_params

    geometry = geometry if geometry is not None else RobotGeometry.from_params()
    viscosity = float(viscosity) if viscosity is not None else fluid_viscosity()
    if height is None:
        sp = sphere_params()
        height = sp.radius + sp.roughness
    key = (geometry.key(), round(viscosity, 15), round(float(height), 12))
    flow = _CACHE.get(key)
    if flow is None:
        flow = _CACHE[key] = RobotFlow(geometry, viscosity, float(height))
    return flow


def clear_cache() -> None:
    """Forget every cached flow solution."""
    _CACHE.clear()
