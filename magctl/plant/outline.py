"""The robot's planar outline, stated once (paper §II, Fig 1): what the drive, the fluid model, the camera, the
tracker, the live view and the animations all use.

The star-shaped Mag-µBot is 310 × 480 × 130 µm³ (§II). Its concave forward face, the one that captures spheres,
is the 480 µm side: the robot travels along its 310 µm dimension. The paper's side-push analysis says so twice:
the gap that avoids contact is "larger than half the robot's width" and its contact threshold sits at
D_g ≈ 370 µm (§IV-D), above 480/2 + 105 = 345 µm but far from 310/2 + 105 = 260 µm. The numbers are in
``models/robot_geometry.toml`` ``[outline]``.

Body frame: ``x`` forward (the heading), ``y`` to the left. The outline is a ``length × width`` star
(:func:`star_outline`): a circular concave notch in the front face and shallow circular concave flanks and rear.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property, lru_cache

import numpy as np

from magctl.config import Params, load_model, model_versions
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
class RobotOutline:
    """The robot's planar outline and thickness, m (``models/robot_geometry.toml`` ``[outline]``).

    Attributes
    ----------
    length : float
        Extent along the heading (the direction of travel), m.
    width : float
        Extent across the heading, m; the concave front face spans it.
    thickness : float
        Height of the plate, m.
    front_notch_depth, front_notch_width : float
        Depth and chord of the concave front face, m.
    side_notch_depth, rear_notch_depth : float
        Depths of the concave flanks and rear, m.
    arc_points : int
        Polygon vertices per concave arc.
    """

    length: float
    width: float
    thickness: float
    front_notch_depth: float
    front_notch_width: float
    side_notch_depth: float
    rear_notch_depth: float
    arc_points: int = 9

    def __post_init__(self):
        for name in ("length", "width", "thickness"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ParameterError(f"robot outline: {name} {value!r} m must be a finite number > 0")
        if int(self.arc_points) != self.arc_points or self.arc_points < 2:
            raise ParameterError(f"robot outline: arc_points {self.arc_points!r} must be an integer >= 2")
        _ = self.vertices   # the notches' checks

    @classmethod
    def from_params(cls, p: Params | None = None) -> RobotOutline:
        """Build from ``models/robot_geometry.toml`` (or its parsed ``p``)."""
        o = (p if p is not None else load_model("robot_geometry")).outline
        return cls(float(o.length), float(o.width), float(o.thickness), float(o.front_notch_depth),
                   float(o.front_notch_width), float(o.side_notch_depth), float(o.rear_notch_depth),
                   int(o.arc_points))

    @cached_property
    def vertices(self) -> np.ndarray:
        """Counter-clockwise outline ``(V, 2)`` in the body frame, m (:func:`star_outline`)."""
        v = star_outline(self.length, self.width, self.front_notch_depth, self.front_notch_width,
                         self.side_notch_depth, self.rear_notch_depth, int(self.arc_points))
        v.setflags(write=False)
        return v

    @cached_property
    def polygon(self) -> Polygon:
        return Polygon(self.vertices)

    @property
    def area(self) -> float:
        """Area of the outline, m² (shoelace formula)."""
        x, y = self.vertices[:, 0], self.vertices[:, 1]
        return float(0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))

    @property
    def centroid(self) -> np.ndarray:
        """Area centroid ``(x, y)`` of the outline in the body frame, m."""
        x, y = self.vertices[:, 0], self.vertices[:, 1]
        cross = x * np.roll(y, -1) - np.roll(x, -1) * y
        return np.array([np.sum((x + np.roll(x, -1)) * cross), np.sum((y + np.roll(y, -1)) * cross)]) / (6 * self.area)

    @property
    def major_axis(self) -> float:
        """Body-frame angle in ``[0, π)`` of the major principal axis of the outline's area (second moments about
        its centroid): π/2 for the paper's robot, wider than it is long. A blob's major axis turned back by this
        angle is the heading's line."""
        v = self.vertices - self.centroid
        x, y = v[:, 0], v[:, 1]
        x1, y1 = np.roll(x, -1), np.roll(y, -1)
        cross = x * y1 - x1 * y
        ixx = np.sum((y * y + y * y1 + y1 * y1) * cross) / 12      # ∫ y² dA
        iyy = np.sum((x * x + x * x1 + x1 * x1) * cross) / 12      # ∫ x² dA
        ixy = np.sum((x * y1 + 2 * x * y + 2 * x1 * y1 + x1 * y) * cross) / 24   # ∫ x y dA
        return float(np.mod(0.5 * np.arctan2(2 * ixy, iyy - ixx), np.pi))

    @property
    def reach(self) -> float:
        """Largest distance from the body origin to the outline, m."""
        return float(np.hypot(self.vertices[:, 0], self.vertices[:, 1]).max())

    def signed_distance(self, x, y) -> np.ndarray:
        """Signed distance from body-frame points ``(x, y)`` to the outline, m (negative inside)."""
        x, y = np.asarray(x, float), np.asarray(y, float)
        dist, _, _ = self.polygon.distance(x, y)
        return np.where(self.polygon.contains(x, y), -dist, dist)

    def scaled(self, factor: float) -> RobotOutline:
        """The same outline in other units (e.g. ``1 / pixel`` for pixels)."""
        f = float(factor)
        return RobotOutline(self.length * f, self.width * f, self.thickness * f, self.front_notch_depth * f,
                            self.front_notch_width * f, self.side_notch_depth * f, self.rear_notch_depth * f,
                            self.arc_points)


@lru_cache(maxsize=8)
def _outline_of(version: tuple) -> RobotOutline:
    return RobotOutline.from_params(load_model("robot_geometry"))


def robot_outline() -> RobotOutline:
    """The outline of the current parameter set (``models_dir()/robot_geometry.toml``), read once per version of
    the file."""
    return _outline_of(model_versions("robot_geometry.toml"))
