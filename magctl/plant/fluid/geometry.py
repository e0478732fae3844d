"""The star-shaped robot as a solid: outline, tilt and surface discretisation (paper §II, §IV-C).

Body frame: ``x`` forward, ``y`` left, ``z`` up from the glass. The outline is a
``length × width`` star with a concave front face (the notch that captures
spheres) and shallow concave flanks and rear, extruded to ``thickness`` and
tilted by ``tilt`` about the edge that rests on the glass. The robot's reference
point (its ``position`` port) is the centre of its footprint on the glass.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from magctl.config import Params, load_model
from magctl.core.errors import ParameterError


def _arc(p0, p1, inward, sagitta, n, endpoint=False):
    """Points from ``p0`` to ``p1`` (``p1`` only with ``endpoint``) bulging by ``sagitta`` along ``inward``."""
    p0, p1, inward = (np.asarray(v, float) for v in (p0, p1, inward))
    t = np.linspace(0.0, 1.0, n + 1 if endpoint else n, endpoint=endpoint)
    chord = np.linalg.norm(p1 - p0)
    line = p0 + t[:, None] * (p1 - p0)
    if sagitta <= 0:
        return line
    rho = (chord**2 / 4 + sagitta**2) / (2 * sagitta)
    offset = np.sqrt(np.maximum(rho**2 - (chord * (t - 0.5)) ** 2, 0.0)) - (rho - sagitta)
    return line + offset[:, None] * inward


def star_outline(length, width, front_notch_depth, front_notch_width, side_notch_depth, rear_notch_depth,
                 arc_points=9) -> np.ndarray:
    """Counter-clockwise outline ``(V, 2)`` [m] of the star robot in its body frame (x forward).

    The front face has a circular concave notch of chord ``front_notch_width`` and
    depth ``front_notch_depth``; flanks and rear are circular arcs of the given depths.
    """
    lx, wy = length / 2, width / 2
    if not 0 < front_notch_width < width:
        raise ParameterError(f"front notch width {front_notch_width * 1e6:.0f} µm must lie in (0, width)")
    if not 0 <= front_notch_depth < length / 2:
        raise ParameterError(f"front notch depth {front_notch_depth * 1e6:.0f} µm must lie in [0, length/2)")
    cw = front_notch_width / 2
    n = int(arc_points)
    parts = [
        np.array([[lx, -wy]]),
        _arc([lx, -cw], [lx, cw], [-1, 0], front_notch_depth, n, endpoint=True),   # concave front face
        _arc([lx, wy], [-lx, wy], [0, -1], side_notch_depth, n),          # left flank
        _arc([-lx, wy], [-lx, -wy], [1, 0], rear_notch_depth, n),         # rear
        _arc([-lx, -wy], [lx, -wy], [0, 1], side_notch_depth, n),         # right flank
    ]
    return np.vstack(parts)


class Polygon:
    """A closed polygon ``(V, 2)`` with its edge data computed once, for repeated point queries.

    Queries take points as coordinate arrays ``x, y`` of any common shape and give the
    same numbers as the array forms :func:`points_in_polygon` and :func:`polygon_distance`
    (the same operations in the same order, only without rebuilding the edges per call).
    """

    def __init__(self, vertices: np.ndarray):
        v = np.array(vertices, dtype=float)
        if v.ndim != 2 or v.shape[1] != 2 or len(v) < 3:
            raise ParameterError(f"a polygon needs (V >= 3, 2) vertices, got shape {v.shape}")
        v.setflags(write=False)
        self.vertices = v
        self.x0, self.y0 = v[:, 0], v[:, 1]
        nxt = np.roll(v, -1, axis=0)
        self.x1, self.y1 = nxt[:, 0], nxt[:, 1]
        self.dx, self.dy = self.x1 - self.x0, self.y1 - self.y0     # edge vectors (also ab of the distance)
        self.ab2 = self.dx * self.dx + self.dy * self.dy

    def contains(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Even-odd test of points ``(x, y)``."""
        x, y = x[..., None], y[..., None]
        crosses = (self.y0 > y) != (self.y1 > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            xint = self.x0 + (y - self.y0) * self.dx / self.dy
        return (crosses & (x < xint)).sum(axis=-1) % 2 == 1

    def distance(self, x: np.ndarray, y: np.ndarray):
        """Distance from points ``(x, y)`` to the boundary, and the nearest boundary point ``(nx, ny)``."""
        shape = np.shape(x)
        x, y = np.ravel(x)[:, None], np.ravel(y)[:, None]
        apx, apy = x - self.x0, y - self.y0
        t = np.minimum(np.maximum((apx * self.dx + apy * self.dy) / self.ab2, 0.0), 1.0)
        px, py = self.x0 + t * self.dx, self.y0 + t * self.dy
        ex, ey = x - px, y - py
        d2 = ex * ex + ey * ey
        # nearest edge of each point, gathered from the flattened (points × edges) tables
        k = np.argmin(d2, axis=-1) + np.arange(0, d2.size, d2.shape[1])
        dist = np.sqrt(d2.take(k))
        return dist.reshape(shape), px.take(k).reshape(shape), py.take(k).reshape(shape)


def _polygon(poly) -> Polygon:
    return poly if isinstance(poly, Polygon) else Polygon(poly)


def points_in_polygon(pts: np.ndarray, poly) -> np.ndarray:
    """Even-odd test of points ``(..., 2)`` against a closed polygon ``(V, 2)`` or :class:`Polygon`."""
    pts = np.asarray(pts, float)
    return _polygon(poly).contains(pts[..., 0], pts[..., 1])


def polygon_distance(pts: np.ndarray, poly):
    """Distance from points ``(..., 2)`` to the polygon boundary and the nearest boundary point.

    Parameters
    ----------
    pts : ndarray (..., 2)
    poly : ndarray (V, 2) or Polygon

    Returns
    -------
    dist : ndarray (...)
    nearest : ndarray (..., 2)
    """
    pts = np.asarray(pts, float)
    dist, nx, ny = _polygon(poly).distance(pts[..., 0], pts[..., 1])
    return dist, np.stack([nx, ny], axis=-1)


@dataclass(frozen=True)
class RobotGeometry:
    """Solid geometry of the tilted star robot.

    Attributes
    ----------
    outline : ndarray (V, 2)
        Body-frame outline [m], centred on the untilted body.
    thickness : float
        [m]
    tilt : float
        Angle to the glass [rad] (paper §IV-C: π/8).
    raised_edge : str
        ``"front"`` or ``"rear"``: which end is lifted.
    clearance : float
        Height of the lowest edge above the glass [m].
    spacing : float
        Spacing of the regularised Stokeslets on the surface [m].
    """

    outline: np.ndarray = field(repr=False)
    thickness: float
    tilt: float
    raised_edge: str = "front"
    clearance: float = 2e-6
    spacing: float = 30e-6

    def __post_init__(self):
        if self.raised_edge not in ("front", "rear"):
            raise ParameterError(f"raised_edge must be 'front' or 'rear', got {self.raised_edge!r}")
        if not 0 <= self.tilt < np.pi / 2:
            raise ParameterError(f"tilt {self.tilt!r} rad must lie in [0, pi/2)")
        if not 0 < self.spacing < self.thickness:
            raise ParameterError(f"surface spacing {self.spacing!r} m must be positive and below the thickness")

    @classmethod
    def from_params(cls, p: Params | None = None) -> RobotGeometry:
        """Build from ``models/robot_geometry.toml``."""
        p = p if p is not None else load_model("robot_geometry")
        o = p.outline
        outline = star_outline(o.length, o.width, o.front_notch_depth, o.front_notch_width, o.side_notch_depth,
                               o.rear_notch_depth, int(o.arc_points))
        d = p.discretisation
        return cls(outline, o.thickness, p.pose.tilt, p.pose.raised_edge, p.pose.clearance, d.spacing)

    def key(self) -> tuple:
        """Hashable identity of the geometry (for flow caches)."""
        return (self.outline.round(12).tobytes(), self.thickness, self.tilt, self.raised_edge, self.clearance,
                self.spacing)

    # --- body ↔ world (robot frame, origin at the footprint centre) ----------------------------
    @cached_property
    def _pivot(self) -> tuple[float, float]:
        xs = self.outline[:, 0]
        sign = 1.0 if self.raised_edge == "front" else -1.0
        pivot = xs.min() if sign > 0 else xs.max()
        foot = np.array([xs.min(), xs.max()])
        foot_w = pivot + (foot - pivot) * np.cos(self.tilt)
        return float(pivot), float(foot_w.mean())

    def to_frame(self, body: np.ndarray) -> np.ndarray:
        """Body coordinates ``(ξ, y, ζ)`` (ζ up through the plate) → robot-frame ``(x, y, z)``."""
        pivot, centre = self._pivot
        s = 1.0 if self.raised_edge == "front" else -1.0
        c, sn = np.cos(self.tilt), np.sin(self.tilt)
        xi, y, zeta = body[..., 0] - pivot, body[..., 1], body[..., 2]
        x = pivot + xi * c - s * zeta * sn - centre
        z = s * xi * sn + zeta * c + self.clearance
        return np.stack([x, y, z], axis=-1)

    def to_body(self, pts: np.ndarray) -> np.ndarray:
        """Inverse of :meth:`to_frame`."""
        pivot, centre = self._pivot
        s = 1.0 if self.raised_edge == "front" else -1.0
        c, sn = np.cos(self.tilt), np.sin(self.tilt)
        x, y, z = pts[..., 0] + centre - pivot, pts[..., 1], pts[..., 2] - self.clearance
        xi = x * c + s * z * sn
        zeta = -s * x * sn + z * c
        return np.stack([xi + pivot, y, zeta], axis=-1)

    def contains(self, pts: np.ndarray) -> np.ndarray:
        """True for robot-frame points ``(..., 3)`` inside the solid."""
        b = self.to_body(np.asarray(pts, float))
        return (b[..., 2] >= 0) & (b[..., 2] <= self.thickness) & points_in_polygon(b[..., :2], self.outline)

    @cached_property
    def footprint(self) -> np.ndarray:
        """Contact outline on the glass ``(V, 2)`` [m]: the bottom face projected, robot frame."""
        body = np.column_stack([self.outline, np.zeros(len(self.outline))])
        return self.to_frame(body)[:, :2]

    # --- discretisation for the flow solver --------------------------------------------------
    def _face_grid(self, step: float, inset: float) -> np.ndarray:
        xs, ys = self.outline[:, 0], self.outline[:, 1]
        gx = np.arange(xs.min() + step / 2, xs.max(), step)
        gy = np.arange(ys.min() + step / 2, ys.max(), step)
        pts = np.stack(np.meshgrid(gx, gy), -1).reshape(-1, 2)
        inside = points_in_polygon(pts, self.outline)
        dist, _ = polygon_distance(pts, self.outline)
        return pts[inside & (dist >= inset)]

    def _perimeter(self, step: float) -> tuple[np.ndarray, np.ndarray]:
        """Points along the outline at ``step`` and their outward normals."""
        a, b = self.outline, np.roll(self.outline, -1, axis=0)
        pts, normals = [], []
        for p, q in zip(a, b, strict=True):
            seg = q - p
            n = max(int(np.ceil(np.linalg.norm(seg) / step)), 1)
            t = (np.arange(n) + 0.5) / n
            pts.append(p + t[:, None] * seg)
            normals.append(np.repeat([[seg[1], -seg[0]] / np.linalg.norm(seg)], n, axis=0))
        return np.vstack(pts), np.vstack(normals)

    def collocation_points(self) -> np.ndarray:
        """Points on the robot's surface (robot frame) ``(P, 3)``, mirror-symmetric about ``y = 0``.

        Ordered as ``[on the axis (n0), y > 0 (n1), their mirror images (n1)]`` so solvers can
        use the symmetry (:attr:`axis_count`).
        """
        h, t = self.spacing, self.thickness
        face = self._face_grid(h, 0.0)
        per, _ = self._perimeter(h)
        levels = np.linspace(0.0, t, max(int(np.ceil(t / h)), 1) + 1)
        body = [np.column_stack([face, np.zeros(len(face))]), np.column_stack([face, np.full(len(face), t)])]
        body += [np.column_stack([per, np.full(len(per), z)]) for z in levels]
        pts = np.vstack(body)
        tol = 1e-3 * h
        axis, upper = pts[np.abs(pts[:, 1]) <= tol], pts[pts[:, 1] > tol]
        axis = axis * [1.0, 0.0, 1.0]
        return self.to_frame(np.vstack([axis, upper, upper * [1.0, -1.0, 1.0]]))

    @property
    def axis_count(self) -> int:
        """Number of collocation points on the symmetry axis (the first ones)."""
        h = self.spacing
        face = self._face_grid(h, 0.0)
        per, _ = self._perimeter(h)
        levels = max(int(np.ceil(self.thickness / h)), 1) + 1
        tol = 1e-3 * h
        return int(2 * (np.abs(face[:, 1]) <= tol).sum() + levels * (np.abs(per[:, 1]) <= tol).sum())

    def is_symmetric(self) -> bool:
        """True when the outline is mirror-symmetric about the body x axis."""
        mirrored = self.outline * [1.0, -1.0]
        dist, _ = polygon_distance(mirrored, self.outline)
        return bool(dist.max() < 1e-9)
