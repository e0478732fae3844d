"""The star-shaped robot as a solid: its outline extruded, tilted and discretised (paper §II, §IV-C).

Body frame: ``x`` forward, ``y`` left, ``z`` up from the glass. The outline is the robot's one
(:mod:`magctl.plant.outline`), extruded to ``thickness`` and tilted by ``tilt`` about the edge
that rests on the glass. The robot's reference
point (its ``position`` port) is the centre of its footprint on the glass.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from magctl.config import Params, load_model
from magctl.core.errors import ParameterError
from magctl.plant.outline import RobotOutline, points_in_polygon, polygon_distance


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
    panel_size : float
        Largest panel edge of the surface mesh [m].
    edge_size : float
        Panel edge at the sharp edges [m].
    grading : float
        Growth of the panel edge per unit distance from a sharp edge.
    wall_ratio : float
        Largest panel edge as a multiple of its height above the glass.
    gap_size : float
        Smallest panel edge near the glass [m].
    """

    outline: np.ndarray = field(repr=False)
    thickness: float
    tilt: float
    raised_edge: str = "front"
    clearance: float = 2e-6
    panel_size: float = 45e-6
    edge_size: float = 12e-6
    grading: float = 0.5
    wall_ratio: float = 1.5
    gap_size: float = 3e-6

    def __post_init__(self):
        if self.raised_edge not in ("front", "rear"):
            raise ParameterError(f"raised_edge must be 'front' or 'rear', got {self.raised_edge!r}")
        if not 0 <= self.tilt < np.pi / 2:
            raise ParameterError(f"tilt {self.tilt!r} rad must lie in [0, pi/2)")
        if not 0 < self.edge_size <= self.panel_size < self.thickness:
            raise ParameterError(f"panel sizes must satisfy 0 < edge_size ({self.edge_size!r} m) <= panel_size "
                                 f"({self.panel_size!r} m) < thickness")
        if not 0 < self.gap_size <= self.edge_size:
            raise ParameterError(f"gap_size {self.gap_size!r} m must lie in (0, edge_size]")
        if self.grading <= 0 or self.wall_ratio <= 0:
            raise ParameterError(f"grading ({self.grading!r}) and wall_ratio ({self.wall_ratio!r}) must be positive")
        if self.clearance <= 0:
            raise ParameterError(f"clearance {self.clearance!r} m must be positive: the robot cannot touch the "
                                 "no-slip glass in a Stokes model")

    @classmethod
    def from_params(cls, p: Params | None = None) -> RobotGeometry:
        """Build from ``models/robot_geometry.toml``."""
        p = p if p is not None else load_model("robot_geometry")
        o = RobotOutline.from_params(p)
        d = p.discretisation
        return cls(np.array(o.vertices), o.thickness, p.pose.tilt, p.pose.raised_edge, p.pose.clearance, d.panel_size,
                   d.edge_size, d.grading, d.wall_ratio, d.gap_size)

    def refined(self, factor: float) -> RobotGeometry:
        """The same robot with every panel size multiplied by ``factor`` (mesh-convergence studies)."""
        import dataclasses

        return dataclasses.replace(self, panel_size=self.panel_size * factor, edge_size=self.edge_size * factor,
                                   gap_size=self.gap_size * factor)

    def key(self) -> tuple:
        """Hashable identity of the geometry (for flow caches)."""
        return (self.outline.round(12).tobytes(), self.thickness, self.tilt, self.raised_edge, self.clearance,
                self.panel_size, self.edge_size, self.grading, self.wall_ratio, self.gap_size)

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

    # --- surface mesh for the boundary-element solver -----------------------------------------
    def _half_outline(self) -> np.ndarray:
        """The outline clipped to ``y >= 0`` (Sutherland–Hodgman against one half-plane), counter-clockwise."""
        v = self.outline
        out = []
        for k in range(len(v)):
            p, q = v[k], v[(k + 1) % len(v)]
            if p[1] >= 0:
                out.append(p)
            if (p[1] >= 0) != (q[1] >= 0):
                t = p[1] / (p[1] - q[1])
                out.append(p + t * (q - p))
        out = np.asarray(out)
        out[np.abs(out[:, 1]) < 1e-15, 1] = 0.0
        keep = np.linalg.norm(out - np.roll(out, -1, axis=0), axis=1) > 1e-12
        return out[keep]

    def surface_mesh(self) -> np.ndarray:
        """Flat triangles ``(T, 3, 3)`` on the ``y > 0`` half of the robot's surface (robot frame, outward
        normals by the right-hand rule); the ``y < 0`` half is its mirror image.

        Meshed with gmsh (Geuzaine & Remacle 2009; frontal-Delaunay) under a size field: ``edge_size``
        at the sharp edges (top and bottom rims, vertical edges at outline corners), growing by
        ``grading`` per unit distance up to ``panel_size``, and no larger than ``wall_ratio`` × the
        height above the glass (the 2 µm gap under the resting edge), but not below ``gap_size``.
        """
        return self._surface_mesh

    @cached_property
    def _surface_mesh(self) -> np.ndarray:
        import gmsh

        half = self._half_outline()
        t = self.thickness
        sign = 1.0 if self.raised_edge == "front" else -1.0
        pivot, _ = self._pivot
        was_init = gmsh.isInitialized()
        if not was_init:
            gmsh.initialize(readConfigFiles=False, interruptible=False)   # leave SIGINT to the caller
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("robot")
        try:
            geo = gmsh.model.geo
            pts = [geo.addPoint(x, y, 0.0) for x, y in half]
            lines = [geo.addLine(pts[k], pts[(k + 1) % len(pts)]) for k in range(len(pts))]
            loop = geo.addCurveLoop(lines)
            base = geo.addPlaneSurface([loop])
            geo.extrude([(2, base)], 0.0, 0.0, t)
            geo.synchronize()
            # curves: the rims (bottom, top) and the vertical edges, except those on the cut y = 0
            rims, verticals = [], []
            for dim, tag in gmsh.model.getEntities(1):
                lo = gmsh.model.getBoundingBox(dim, tag)
                on_cut = abs(lo[1]) < 1e-12 and abs(lo[4]) < 1e-12
                if on_cut:
                    continue
                if abs(lo[2] - lo[5]) < 1e-12:
                    rims.append(tag)
                else:
                    verticals.append((tag, lo[0], lo[1]))
            corners = []
            for k in range(len(half)):
                a, b, c = half[k - 1], half[k], half[(k + 1) % len(half)]
                if abs(b[1]) < 1e-12:
                    continue
                u, w = b - a, c - b
                turn = abs(np.arctan2(u[0] * w[1] - u[1] * w[0], u @ w))
                if turn > np.radians(25):
                    corners.append(b)
            sharp_vertical = [tag for tag, x, y in verticals
                              if any(np.hypot(x - cx, y - cy) < 1e-12 for cx, cy in corners)]
            f = gmsh.model.mesh.field
            dist = f.add("Distance")
            f.setNumbers(dist, "CurvesList", rims + sharp_vertical)
            f.setNumber(dist, "Sampling", 200)
            thr = f.add("Threshold")
            f.setNumber(thr, "InField", dist)
            f.setNumber(thr, "SizeMin", self.edge_size)
            f.setNumber(thr, "SizeMax", self.panel_size)
            f.setNumber(thr, "DistMin", 0.0)
            f.setNumber(thr, "DistMax", (self.panel_size - self.edge_size) / self.grading)
            # height above the glass of a body point (x, y, z) (see to_frame)
            c, sn = np.cos(self.tilt), np.sin(self.tilt)
            a0 = self.clearance - sign * sn * pivot                         # plain decimals for gmsh's parser
            height = f"({sign * sn:.15f}*x + {c:.15f}*z + {a0:.15f})".replace("+ -", "- ")
            wall = f.add("MathEval")
            f.setString(wall, "F", f"max({self.gap_size:.15f}, {self.wall_ratio:.15f}*{height})")
            both = f.add("Min")
            f.setNumbers(both, "FieldsList", [thr, wall])
            f.setAsBackgroundMesh(both)
            gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
            gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
            gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
            gmsh.option.setNumber("Mesh.Algorithm", 6)
            gmsh.model.mesh.generate(2)
            tris = []
            for dim, tag in gmsh.model.getEntities(2):
                lo = gmsh.model.getBoundingBox(dim, tag)
                if abs(lo[1]) < 1e-12 and abs(lo[4]) < 1e-12:
                    continue                                    # the cut plane y = 0 is not a surface
                _, node_tags = gmsh.model.mesh.getElementsByType(2, tag)      # 3-node triangles
                tris.append(np.asarray(node_tags, np.int64).reshape(-1, 3))
            node_ids, coords, _ = gmsh.model.mesh.getNodes()
            xyz = np.asarray(coords).reshape(-1, 3)
            lookup = np.zeros(int(node_ids.max()) + 1, np.int64)
            lookup[np.asarray(node_ids, np.int64)] = np.arange(len(node_ids))
            tri = xyz[lookup[np.vstack(tris)]]
        finally:
            gmsh.model.remove()
            if not was_init:
                gmsh.finalize()
        # orient outward: the normal must point away from the solid (probe just outside the centroid)
        nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
        cen = tri.mean(axis=1)
        probe = cen + 1e-3 * self.edge_size * nrm
        inside = ((probe[:, 2] > 0) & (probe[:, 2] < t)
                  & points_in_polygon(probe[:, :2], self.outline))
        tri[inside] = tri[inside][:, ::-1]
        return self.to_frame(tri)

    def is_symmetric(self) -> bool:
        """True when the outline is mirror-symmetric about the body x axis."""
        mirrored = self.outline * [1.0, -1.0]
        dist, _ = polygon_distance(mirrored, self.outline)
        return bool(dist.max() < 1e-9)
