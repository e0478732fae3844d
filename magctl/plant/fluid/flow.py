"""The Stokes flow of the translating robot above the glass, with cached maps in the robot frame.

The robot (geometry and surface mesh from :mod:`magctl.plant.fluid.geometry`) is a
rigid body near the no-slip glass in the oil layer of :class:`magctl.plant.fluid.domain.Domain`.
Its flow is solved by the boundary-element method of :mod:`magctl.plant.fluid.bem`
(Blake's tensor: the glass is exact) for unit translation along the body ``x`` and
``y`` axes; by Stokes linearity the flow of any in-plane velocity is their
combination (paper §III: position, not velocity, sets the displacement).

Bounded layers (:class:`Domain`):

* ``lid`` — a no-slip plane at ``z = H``, discretised as panels on a disc of radius
  :data:`LID_RADIUS` × H;
* ``free_surface`` — a flat stress-free top at ``z = H`` is, by reflection, the symmetric
  half of a channel of depth 2H: the robot and a lid at ``z = 2H``, each also seen through the
  surface (``bem.PanelSet.reflect``), so the glass stays exact for the mirrored half too.

The flow at the sphere-centre height is sampled once on a grid in the robot frame
(both motions, three components), so a frame of a batched simulation is a table
look-up, a scaling by the body-frame velocity and a rotation. Off the map the panel
forces are summed as singular Blake Stokeslets at the panel centroids (exact to
O((panel/r)²)). Solutions are cached in memory by geometry, viscosity, height and
domain, and on disk (``$MAGCTL_CACHE`` or ``~/.cache/magctl``) under a hash of every
input and :data:`SOLVER_VERSION`, so a cold process loads instead of solving.
"""

from __future__ import annotations

import hashlib
import os
import pathlib
from dataclasses import dataclass, field

import numpy as np

from magctl.plant.fluid import bem
from magctl.plant.fluid.domain import Domain
from magctl.plant.fluid.geometry import RobotGeometry
from magctl.plant.fluid.stokes import regularized_blake_velocity

SOLVER_VERSION = "bem-2"
"""Bumped whenever the solver's numbers change, so stale on-disk maps are never read."""

LID_RADIUS = 6.0
"""Radius of the discretised lid disc in units of its height (truncation check in docs/fluid.md §3)."""

LID_PANELS = 0.25
"""Lid panel edge at the centre in units of its clearance over the robot; it grows with r as (1 + r/H)."""

FREE_SURFACE_MAP = 6.0
"""Under a free surface the map reaches ±FREE_SURFACE_MAP × H (at least the default ±1.5 mm)."""

LID_FAR = 0.5
"""Off the map a lid panel is summed in pieces no larger than LID_FAR × its distance to the map plane."""

FAR_CELL = 60e-6
"""Cell size [m] in which the robot's panel forces are gathered for the off-map sum (≥ 1.2 mm away)."""

# a regular tetrahedron of unit vectors: Σ t_a = 0, Σ t_a t_aᵀ = (4/3) I
_TETRA = np.array([[1.0, 1.0, 1.0], [1.0, -1.0, -1.0], [-1.0, 1.0, -1.0], [-1.0, -1.0, 1.0]]) / np.sqrt(3.0)


def far_field_points(points: np.ndarray, forces: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """Point forces that reproduce ``forces (K, S, 3)`` at ``points (S, 3)`` far away, to second order.

    The points are gathered into cubic cells of edge ``cell``; each cell's total force ``F`` and first
    moment ``M_ij = Σ (y − ȳ)_i f_j`` about its centroid ``ȳ`` are carried by four point forces at
    ``ȳ + s t_a`` (a regular tetrahedron, ``s`` ≤ cell/2 and above the glass) with
    ``F_a = F/4 + (3/(4s)) Mᵀ t_a`` — the multipole expansion then differs from the panel sum only at
    the second moments, O((cell/r)²) of the cell's flow at a distance r.
    """
    key = np.floor(points / cell).astype(np.int64)
    _, cell_of, count = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    cell_of = cell_of.ravel()
    n_cells = len(count)
    centre = np.zeros((n_cells, 3))
    np.add.at(centre, cell_of, points)
    centre /= count[:, None]
    arm = points - centre[cell_of]
    total = np.zeros((forces.shape[0], n_cells, 3))
    moment = np.zeros((forces.shape[0], n_cells, 3, 3))
    for k in range(forces.shape[0]):
        np.add.at(total[k], cell_of, forces[k])
        np.add.at(moment[k], cell_of, arm[:, :, None] * forces[k][:, None, :])
    s = np.minimum(cell / 2.0, 0.5 * centre[:, 2])                       # keep the points above the glass
    out_pts = (centre[:, None, :] + s[:, None, None] * _TETRA[None]).reshape(-1, 3)
    mt = np.swapaxes(moment, -1, -2)                                      # Mᵀ
    f = total[:, :, None, :] / 4.0 + 0.75 / s[None, :, None, None] * np.einsum("kcij,aj->kcai", mt, _TETRA)
    return out_pts, f.reshape(forces.shape[0], -1, 3)


def _axis(half: float, fine_half: float, fine_step: float, growth: float = 1.25, start: float = 0.0) -> np.ndarray:
    """Non-negative grid nodes: ``fine_step`` up to ``fine_half``, then growing steps to ``half``."""
    nodes = list(np.arange(start, fine_half + fine_step / 2, fine_step))
    step = fine_step
    while nodes[-1] < half:
        step *= growth
        nodes.append(min(nodes[-1] + step, half))
    return np.asarray(nodes)


def lid_half(height: float, radius: float, size: float, growth_length: float) -> np.ndarray:
    """Triangles ``(T, 3, 3)`` of the ``y > 0`` half of a disc of ``radius`` at ``z = height``.

    Rings of panels whose edge is ``size (1 + r / growth_length)``; normals point down (into the layer).
    """
    rings = [0.0]
    while rings[-1] < radius:
        rings.append(min(rings[-1] + size * (1 + rings[-1] / growth_length), radius))
    tris = []
    prev = None
    for r in rings[1:]:
        m = max(2, int(np.ceil(np.pi * r / (size * (1 + r / growth_length)))))
        th = np.linspace(0.0, np.pi, m + 1)
        ring = np.column_stack([r * np.cos(th), r * np.sin(th)])
        if prev is None:
            for k in range(m):
                tris.append([[0.0, 0.0], ring[k + 1], ring[k]])
        else:
            # stitch the two rings by advancing along whichever is behind in angle
            i = j = 0
            ti, tj = np.linspace(0.0, np.pi, len(prev)), th
            while i < len(prev) - 1 or j < len(ring) - 1:
                if j < len(ring) - 1 and (i == len(prev) - 1 or tj[j + 1] <= ti[i + 1]):
                    tris.append([prev[i], ring[j + 1], ring[j]])
                    j += 1
                else:
                    tris.append([prev[i], prev[i + 1], ring[j]])
                    i += 1
        prev = ring
    t = np.asarray(tris)
    return np.concatenate([t, np.full(t.shape[:2] + (1,), height)], axis=2)


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
    domain : Domain
        What bounds the oil above the glass.
    tris : ndarray (S, 3, 3)
        Every panel (robot, its mirror images, lid) in the robot frame [m].
    density : ndarray (2, S, 3)
        Force per area the panels exert on the fluid for unit velocity along body x and body y
        [N/m² per m/s].
    reflect : ndarray (S,)
        Mirror plane of a panel seen through the free surface (:class:`bem.PanelSet`), NaN for none.
    robot_panels : ndarray (S,) bool
        The panels on the robot itself (not a lid or an image).
    points : ndarray (M, 3)
        Singular Blake Stokeslets used off the map (robot frame): the panel forces gathered by
        :func:`far_field_points`, lid panels in pieces.
    forces : ndarray (2, M, 3)
        Their strengths [N per m/s].
    eps : float
        Regularisation length of the off-map Stokeslets: 0 (singular Blake Stokeslets).
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
    domain: Domain = field(default_factory=Domain)
    map_half: float = 1.5e-3
    map_step: float = 15e-6
    disk_cache: bool = True
    tris: np.ndarray = field(init=False, repr=False)
    density: np.ndarray = field(init=False, repr=False)
    reflect: np.ndarray = field(init=False, repr=False)
    robot_panels: np.ndarray = field(init=False, repr=False)
    points: np.ndarray = field(init=False, repr=False)
    forces: np.ndarray = field(init=False, repr=False)
    eps: float = field(init=False, default=0.0)
    gx: np.ndarray = field(init=False, repr=False)
    gy: np.ndarray = field(init=False, repr=False)
    maps: np.ndarray = field(init=False, repr=False)
    inside: np.ndarray = field(init=False, repr=False)

    _STORED = ("tris", "reflect", "density", "robot_panels", "gx", "gy", "maps", "inside")

    def __post_init__(self):
        if self.viscosity <= 0:
            raise ValueError(f"viscosity must be positive, got {self.viscosity!r} Pa*s")
        if self.height <= 0:
            raise ValueError(f"map height must be above the glass, got {self.height!r} m")
        if not isinstance(self.domain, Domain):
            raise TypeError(f"domain must be a magctl.plant.fluid.domain.Domain, got {type(self.domain).__name__}")
        if self.domain.kind == "box":
            raise ValueError("the 'box' domain (the paper's COMSOL model) needs a finite-element solver; "
                             "the boundary-element flow supports 'unbounded', 'lid' and 'free_surface'")
        if self.domain.bounded and self.height >= self.domain.depth:
            raise ValueError(f"map height {self.height!r} m must lie below the oil depth {self.domain.depth!r} m")
        if self.domain.kind == "free_surface":
            # the off-map sum cannot carry the surface's images (the compiled kernel has only the glass's):
            # map out to 6H, where the layer's far field (a 2-D dipole, ~ (H/r)^2) is small
            self.map_half = max(self.map_half, FREE_SURFACE_MAP * self.domain.depth)
        path = self._cache_path() if self.disk_cache else None
        if path is not None and path.exists():
            with np.load(path) as data:
                for name in self._STORED:
                    setattr(self, name, data[name])
        else:
            self._solve()
            self._build_maps()
            if path is not None:
                self._store(path)
        self.points, self.forces = self._far_field()
        self.eps = 0.0

    # --- the on-disk cache -----------------------------------------------------------------
    def cache_key(self) -> str:
        """Hash of every input of the solution and the solver version (with the mesher's)."""
        import gmsh

        h = hashlib.sha256()
        for part in (SOLVER_VERSION, gmsh.__version__, repr(self.geometry.key()), repr(round(self.viscosity, 15)),
                     repr(round(self.height, 12)), repr(self.domain.key()), repr((self.map_half, self.map_step)),
                     repr((bem.NEAR, bem.MID, bem.FAR, bem.MAX_DEPTH, LID_RADIUS, LID_PANELS, LID_FAR, FAR_CELL))):
            h.update(part.encode())
        return h.hexdigest()[:24]

    def _cache_path(self) -> pathlib.Path | None:
        root = os.environ.get("MAGCTL_CACHE")
        base = pathlib.Path(root) if root else pathlib.Path.home() / ".cache" / "magctl"
        return base / "robot_flow" / f"{self.cache_key()}.npz"

    def _store(self, path: pathlib.Path) -> None:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(f".{os.getpid()}.tmp.npz")
            np.savez(tmp, **{name: getattr(self, name) for name in self._STORED})
            os.replace(tmp, path)
        except OSError:
            pass                     # a read-only cache directory only costs a re-solve next time

    # --- the solve ---------------------------------------------------------------------
    def _panel_sets(self) -> tuple[bem.PanelSet, bem.PanelSet, np.ndarray]:
        """Even (body-x motion) and odd (body-y motion) panel sets, and which panels are the robot's own.

        Independent panels: the robot's ``y > 0`` half, then the lid's. Copies: their y-mirror images
        and, for a free surface, everything again seen through the surface ``z = H``
        (:class:`bem.PanelSet` ``reflect``), which makes ``z = H`` a plane of symmetry of the flow.
        """
        robot = self.geometry.surface_mesh()
        if not self.geometry.is_symmetric():
            raise ValueError("the robot outline must be mirror-symmetric about its x axis (y -> -y)")
        d = self.domain
        half, body = robot, np.zeros(len(robot), np.int64)
        if d.bounded:
            top = d.depth if d.kind == "lid" else 2.0 * d.depth
            clear = top - robot[..., 2].max()                      # lid above the robot (or its mirror)
            lid = lid_half(top, LID_RADIUS * top, LID_PANELS * min(clear, top), top)
            half = np.concatenate([robot, lid])
            body = np.concatenate([body, np.full(len(lid), -1, np.int64)])
        n = len(half)
        planes = [np.nan] + ([d.depth] if d.kind == "free_surface" else [])
        sets = []
        for par in ((1.0, -1.0, 1.0), (-1.0, 1.0, -1.0)):
            tris, sign, reflect = [], [], []
            for c in planes:
                for mirror_y in (False, True):
                    tris.append(bem.mirrored(half, 1) if mirror_y else half)
                    sign.append(np.tile(par if mirror_y else (1.0, 1.0, 1.0), (n, 1)))
                    reflect.append(np.full(n, c))
            copies = len(tris)
            sets.append(bem.PanelSet(np.concatenate(tris), np.tile(np.arange(n), copies), np.concatenate(sign),
                                     np.tile(body, copies), n, np.concatenate(reflect)))
        own = np.zeros(len(sets[0].tris), bool)
        own[:len(robot)] = True
        own[n:n + len(robot)] = True                                # the robot's y-mirror half
        return sets[0], sets[1], own

    def _solve(self) -> None:
        even, odd, own = self._panel_sets()
        n = even.n_independent
        nr = int(own[:n].sum())
        dens = []
        for k, ps in enumerate((even, odd)):
            rhs = np.zeros((1, n, 3))
            rhs[0, :nr, k] = 1.0
            dens.append(bem.solve(ps, rhs, self.viscosity, deflate=(k == 0))[0])
        self.tris = even.tris
        self.reflect = even.reflect
        self.density = np.stack(dens)
        self.robot_panels = own

    def _far_field(self) -> tuple[np.ndarray, np.ndarray]:
        """Point forces for the off-map sum: the robot's panels (and their images) gathered by
        :func:`far_field_points`, lid panels split into pieces small against their distance to the map
        plane. A panel seen through the free surface enters as the mirrored point with the mirrored
        force (its wall images are then the glass's, not the mirror of them in the surface: an
        approximation, see docs/fluid.md §3 on the map edge)."""
        area = bem.areas(self.tris)
        f = self.density * area[None, :, None]
        lid = self._lid_panels()
        refl = ~np.isnan(self.reflect)
        flip = np.array([1.0, 1.0, -1.0])
        pts, frc = [], []
        for on_lid in (False, True):
            for mirrored in (False, True):
                sel = (lid == on_lid) & (refl == mirrored)
                if not sel.any():
                    continue
                if on_lid:
                    top = self.domain.depth if self.domain.kind == "lid" else 2.0 * self.domain.depth
                    p, q = self._lid_pieces(sel, f, LID_FAR * (top - self.height))
                else:
                    p, q = bem.centroids(self.tris[sel]), f[:, sel]
                if mirrored:
                    c = self.reflect[sel][0]
                    p, q = p * flip + [0.0, 0.0, 2.0 * c], q * flip
                keep = p[:, 2] > 0                                   # a point force on the glass has no flow
                p, q = p[keep], q[:, keep]
                if not on_lid:
                    p, q = far_field_points(p, q, FAR_CELL)
                pts.append(p)
                frc.append(q)
        return np.concatenate(pts), np.concatenate(frc, axis=1)

    def _lid_pieces(self, lid: np.ndarray, f: np.ndarray, size: float) -> tuple[np.ndarray, np.ndarray]:
        """Centroids ``(L', 3)`` and forces ``(2, L', 3)`` of the lid panels, each split into ``4^k`` equal
        pieces no larger than ``size``."""
        tris, fl = self.tris[lid], f[:, lid]          # lid: a boolean mask of the panels to split
        edge = np.linalg.norm(tris - np.roll(tris, 1, axis=1), axis=2).max(axis=1)
        levels = np.maximum(np.ceil(np.log2(np.maximum(edge / size, 1.0))), 0).astype(int)
        pts, frc = [], []
        for k in np.unique(levels):
            sel = levels == k
            pieces = tris[sel]
            for _ in range(k):
                a, b, c = pieces[:, 0], pieces[:, 1], pieces[:, 2]
                ab, bc, ca = (a + b) / 2, (b + c) / 2, (c + a) / 2
                pieces = np.concatenate([np.stack(t, axis=1) for t in ((a, ab, ca), (ab, b, bc), (ca, bc, c),
                                                                        (ab, bc, ca))])
            m = 4**k
            pts.append(pieces.mean(axis=1))
            frc.append(np.tile(fl[:, sel] / m, (1, m, 1)))
        if not pts:
            return np.zeros((0, 3)), np.zeros((2, 0, 3))
        return np.concatenate(pts), np.concatenate(frc, axis=1)

    def _lid_panels(self) -> np.ndarray:
        """Panels on a lid (flat, at the lid height)."""
        if not self.domain.bounded:
            return np.zeros(len(self.tris), bool)
        top = self.domain.depth if self.domain.kind == "lid" else 2.0 * self.domain.depth
        return np.all(np.abs(self.tris[..., 2] - top) < 1e-12 * top, axis=1)

    def velocity_exact(self, pts: np.ndarray) -> np.ndarray:
        """Flow ``(2, P, 3)`` at robot-frame points ``(P, 3)`` in the fluid for unit body-x and body-y motion
        (panel integrals with near-singular quadrature)."""
        pts = np.asarray(pts, float).reshape(-1, 3)
        return bem.layer_velocity(pts, self.tris, self.density, self.viscosity, reflect=self.reflect)

    def velocity_far(self, pts: np.ndarray) -> np.ndarray:
        """Flow ``(2, P, 3)`` of the off-map point forces (:attr:`points`, :attr:`forces`): what the look-up
        uses beyond the map, exact to O((cell/r)²)."""
        pts = np.asarray(pts, float).reshape(-1, 3)
        return regularized_blake_velocity(pts, self.points, self.forces, self.viscosity, 0.0)

    def drag(self) -> np.ndarray:
        """Hydrodynamic force on the robot ``(2, 3)`` [N per m/s] for the two unit motions."""
        area = bem.areas(self.tris)[self.robot_panels]
        return -(self.density[:, self.robot_panels] * area[None, :, None]).sum(axis=1)

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

        Bilinear in the map; beyond the map the panel forces are summed as point Stokeslets.
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
            far = self.velocity_far(pts)
            vbx, vby = vx[outside][:, None], vy[outside][:, None]
            exact = vbx * far[0] + vby * far[1]
            ux, uy, uz = ux.copy(), uy.copy(), uz.copy()
            ux[outside], uy[outside], uz[outside] = exact[:, 0], exact[:, 1], exact[:, 2]
        return ux, uy, uz


_CACHE: dict[tuple, RobotFlow] = {}


def flow_defaults(geometry: RobotGeometry | None, viscosity: float | None, height: float | None,
                  domain: Domain | None) -> tuple[RobotGeometry, float, float, Domain]:
    """The flow's inputs with what is not given read from ``models/``: the robot geometry, μ = ν ρ,
    the map height R + ε (the sphere centre resting on the glass) and the oil's domain."""
    from magctl.plant.fluid.params import fluid_viscosity, sphere_params

    geometry = geometry if geometry is not None else RobotGeometry.from_params()
    viscosity = float(viscosity) if viscosity is not None else fluid_viscosity()
    if height is None:
        sp = sphere_params()
        height = sp.radius + sp.roughness
    return geometry, viscosity, float(height), domain if domain is not None else Domain.from_params()


def robot_flow(geometry: RobotGeometry | None = None, viscosity: float | None = None,
               height: float | None = None, domain: Domain | None = None) -> RobotFlow:
    """The cached :class:`RobotFlow` for this geometry, viscosity, map height and oil domain.

    Defaults come from ``models/robot_geometry.toml``, ``models/fluid.toml`` (μ = ν ρ and
    ``[domain]``) and ``models/sphere.toml`` (height R + ε). A new key (any changed parameter)
    solves anew (or loads that key's solution from the disk cache).
    """
    geometry, viscosity, height, domain = flow_defaults(geometry, viscosity, height, domain)
    key = (geometry.key(), round(viscosity, 15), round(float(height), 12), domain.key())
    flow = _CACHE.get(key)
    if flow is None:
        flow = _CACHE[key] = RobotFlow(geometry, viscosity, float(height), domain)
    return flow


def clear_cache() -> None:
    """Forget every flow solution cached in memory (the disk cache stays)."""
    _CACHE.clear()
