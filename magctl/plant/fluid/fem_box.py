"""The paper's COMSOL box (§IV-C) as a finite-element Stokes problem: the robot's flow in a bounded box.

Paper §IV-C: the robot is held still at π/8 to the glass inside a bounding box; the
front and rear faces are an inlet and an outlet "with a flow of 0.4 mm/s", the ground
moves at the free-stream velocity, every other outer face is a symmetry (slip) face,
the robot is no-slip, half the robot is modelled (mirror plane ``y = 0``), and the
free-stream velocity is subtracted afterwards to give the flow of a robot moving in
stagnant oil. This module builds that model:

* :func:`box_mesh` — the half box ``x0 ≤ x ≤ x0 + L`` (the robot's reference point at
  ``robot_x`` from the box centre), ``0 ≤ y ≤ W``, ``0 ≤ z ≤ H`` minus the robot solid
  of :class:`~magctl.plant.fluid.geometry.RobotGeometry` (the same outline, tilt about
  the resting edge and clearance as the boundary-element model), meshed in tetrahedra by
  gmsh (OpenCASCADE) with a size field fine on the robot and finest at the resting edge;
* :func:`solve_stokes` — Taylor–Hood P2–P1 Stokes (scikit-fem) with the viscous form
  ``2μ ε(u):ε(v)``, so natural boundaries are traction-free; Dirichlet data per face and
  component; a sparse direct solve, or MINRES with a block-diagonal preconditioner
  (algebraic multigrid on the viscous block, the scaled pressure mass diagonal on the
  Schur complement; Elman, Silvester & Wathen 2014 §4.2) on larger meshes;
* :func:`box_solve` — the paper's boundary conditions for unit robot motion along body x
  (and, by the same construction with the inlet on the side face, along body y);
* :func:`box_flow_maps` — the lab-frame flow per unit robot speed on a robot-frame grid at
  the sphere-centre height, laid out like :attr:`magctl.plant.fluid.flow.RobotFlow.maps`
  and cached on disk;
* :class:`BoxFlow` — those maps behind :class:`~magctl.plant.fluid.flow.RobotFlow`'s
  look-up interface, for :class:`magctl.plant.sphere.Spheres` (``flow=``).

The box ends the oil: points outside it get zero flow. scikit-fem and gmsh are the
optional extra ``fem`` (``pip install 'magctl[fem]'``).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import resource
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from magctl.core.errors import MagctlError, ParameterError
from magctl.core.units import UM
from magctl.plant.fluid.domain import Domain
from magctl.plant.fluid.flow import RobotFlow, flow_defaults
from magctl.plant.fluid.geometry import RobotGeometry

CACHE_VERSION = 1
"""Bumped whenever a change of this module changes the maps it would compute."""

FACES = ("x_min", "x_max", "y_min", "y_max", "z_min", "z_max")


class MissingExtraError(MagctlError, ImportError):
    """The optional ``fem`` extra (scikit-fem, gmsh) is not installed."""


def require_fem():
    """Import and return ``(skfem, gmsh)``, or raise :class:`MissingExtraError` naming the extra."""
    try:
        import gmsh
        import skfem
    except ImportError as exc:
        raise MissingExtraError(
            f"the finite-element box model needs scikit-fem and gmsh ({exc.name} is missing): "
            "pip install 'magctl[fem]'") from exc
    return skfem, gmsh


# --- meshes --------------------------------------------------------------------------------
@dataclass
class TetMesh:
    """A tetrahedral mesh and its boundary facets sorted by the face they lie on.

    Attributes
    ----------
    mesh : skfem.MeshTet
        Coordinates in metres.
    facets : dict[str, ndarray]
        Boundary facet indices per name: ``x_min … z_max`` for the box faces, ``body``
        for every other boundary facet (the robot, or the obstacle of a test problem).
    mesh_time : float
        Seconds spent in gmsh.
    """

    mesh: object
    facets: dict
    mesh_time: float = 0.0

    @property
    def n_tets(self) -> int:
        return int(self.mesh.t.shape[1])


def _gmsh_to_skfem(gmsh, skfem, scale: float = UM):
    """The current gmsh model's linear tetrahedra as ``skfem.MeshTet`` (coordinates × ``scale``)."""
    tags, coords, _ = gmsh.model.mesh.getNodes()
    etypes, _, enodes = gmsh.model.mesh.getElements(3)
    if 4 not in list(etypes):
        raise MagctlError("gmsh produced no linear tetrahedra")
    conn = np.asarray(enodes[list(etypes).index(4)], dtype=np.int64).reshape(-1, 4)
    index = np.full(int(tags.max()) + 1, -1, dtype=np.int64)
    index[tags.astype(np.int64)] = np.arange(len(tags))
    t = index[conn]
    used = np.unique(t)
    renumber = np.full(len(tags), -1, dtype=np.int64)
    renumber[used] = np.arange(len(used))
    p = coords.reshape(-1, 3)[used] * scale
    return skfem.MeshTet(np.ascontiguousarray(p.T), np.ascontiguousarray(renumber[t].T))


def classify_facets(mesh, bounds, tol: float) -> dict:
    """Boundary facets of ``mesh`` on the six planes of ``bounds = ((x0, x1), (y0, y1), (z0, z1))``; the rest
    are ``body``. A facet lies on a plane when all three of its vertices are within ``tol`` of it."""
    bf = mesh.boundary_facets()
    fv = mesh.p[:, mesh.facets[:, bf]]            # (3 coords, 3 vertices, F)
    out, taken = {}, np.zeros(len(bf), bool)
    for axis in range(3):
        for side, name in ((0, FACES[2 * axis]), (1, FACES[2 * axis + 1])):
            on = np.all(np.abs(fv[axis] - bounds[axis][side]) <= tol, axis=0)
            out[name] = bf[on & ~taken]
            taken |= on
    out["body"] = bf[~taken]
    return out


def _robot_affine(geometry: RobotGeometry) -> np.ndarray:
    """The affine map body → robot frame of :meth:`RobotGeometry.to_frame` as a 3 × 4 matrix (metres)."""
    base = geometry.to_frame(np.zeros(3))
    cols = [geometry.to_frame(e) - base for e in np.eye(3)]
    return np.column_stack([*cols, base])


@dataclass(frozen=True)
class MeshSpec:
    """Element sizes of the box mesh [m].

    Attributes
    ----------
    size : float
        On the robot's surface.
    gap_size : float or None
        At the robot's lowest edge (the ``clearance`` gap); ``None``: ``max(clearance, size / 6)``.
    far_size : float or None
        Far from the robot; ``None``: ``8 × size``.
    grading : float
        Growth of the element size with distance from the robot (size increase per unit distance).
    """

    size: float = 30e-6
    gap_size: float | None = None
    far_size: float | None = None
    grading: float = 0.3

    def resolved(self, geometry: RobotGeometry) -> tuple[float, float, float, float]:
        """``(size, gap_size, far_size, grading)`` with defaults filled in."""
        if not (math.isfinite(self.size) and self.size > 0):
            raise ParameterError(f"mesh size must be positive, got {self.size!r} m")
        if not self.grading > 0:
            raise ParameterError(f"mesh grading must be positive, got {self.grading!r}")
        gap = self.gap_size if self.gap_size is not None else max(geometry.clearance, self.size / 6)
        far = self.far_size if self.far_size is not None else 8 * self.size
        if not (0 < gap <= self.size <= far):
            raise ParameterError(f"mesh sizes must satisfy 0 < gap_size ({gap!r}) <= size ({self.size!r}) "
                                 f"<= far_size ({far!r}) m")
        return float(self.size), float(gap), float(far), float(self.grading)


def _box_bounds(domain: Domain, robot_x: float):
    if domain.kind != "box":
        raise ParameterError(f"the finite-element model needs a fluid domain of kind 'box', got {domain.kind!r}")
    x0 = -domain.box_length / 2 - robot_x
    return (x0, x0 + domain.box_length), (0.0, domain.box_half_width), (0.0, domain.depth)


def box_mesh(geometry: RobotGeometry, domain: Domain, spec: MeshSpec = MeshSpec(), robot_x: float = 0.0,
             robot: bool = True) -> TetMesh:
    """Tetrahedral mesh of the half box minus the half robot (paper §IV-C), robot frame, metres.

    In the robot frame the box spans ``-L/2 - robot_x ≤ x ≤ L/2 - robot_x`` (the robot's reference
    point sits ``robot_x`` ahead of the box centre), ``0 ≤ y ≤ W``, ``0 ≤ z ≤ H``. The
    robot is the outline of ``geometry`` extruded to its thickness and placed by the same affine
    map as :meth:`RobotGeometry.to_frame` (tilt about the resting edge, clearance above the glass).
    ``robot=False`` meshes the empty box (for checks).
    """
    size, gap, far, grading = spec.resolved(geometry)
    (x0, x1), (y0, y1), (z0, z1) = _box_bounds(domain, robot_x)
    skfem, gmsh = require_fem()
    if robot:
        corners = geometry.to_frame(np.array([[x, y, z] for x, y in geometry.outline
                                              for z in (0.0, geometry.thickness)]))
        lo, hi = corners.min(axis=0), corners.max(axis=0)
        if lo[0] <= x0 or hi[0] >= x1 or hi[1] >= y1 or hi[2] >= z1:
            raise ParameterError("the robot does not fit inside the box: widen it or move robot_x")
    t0 = time.perf_counter()
    gmsh.initialize(interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("box")
        occ = gmsh.model.occ
        s = 1.0 / UM   # gmsh works in micrometres (OpenCASCADE's absolute tolerance is 1e-7 of the model unit)
        box = occ.addBox(x0 * s, y0 * s, z0 * s, (x1 - x0) * s, (y1 - y0) * s, (z1 - z0) * s)
        if robot:
            pts = [occ.addPoint(x * s, y * s, 0.0) for x, y in geometry.outline]
            lines = [occ.addLine(pts[i], pts[(i + 1) % len(pts)]) for i in range(len(pts))]
            face = occ.addPlaneSurface([occ.addCurveLoop(lines)])
            ext = occ.extrude([(2, face)], 0.0, 0.0, geometry.thickness * s)
            vol = [dt for dt in ext if dt[0] == 3]
            a = _robot_affine(geometry)
            a[:, 3] *= s
            occ.affineTransform(vol, a.ravel().tolist())
            occ.cut([(3, box)], vol)
        occ.synchronize()
        fields = []
        if robot:
            bb = (x0 * s, y0 * s, z0 * s, x1 * s, y1 * s, z1 * s)
            on_box = set()
            for k, v in enumerate(bb):
                lo_hi = [list(bb[:3]), list(bb[3:])]
                lo_hi[0][k % 3] = lo_hi[1][k % 3] = v
                tol = 1e-3
                found = gmsh.model.getEntitiesInBoundingBox(lo_hi[0][0] - tol, lo_hi[0][1] - tol, lo_hi[0][2] - tol,
                                                            lo_hi[1][0] + tol, lo_hi[1][1] + tol, lo_hi[1][2] + tol, 2)
                on_box |= {t for _, t in found}
            robot_faces = [t for _, t in gmsh.model.getEntities(2) if t not in on_box]
            low = geometry.clearance * s + 0.5 * gap * s
            # the robot's edges within half a gap element of its lowest point: where the oil film is thinnest
            low_curves = [t for _, t in gmsh.model.getEntities(1)
                          if gmsh.model.getBoundingBox(1, t)[2] <= low and not _on_box_curve(gmsh, t, bb)]
            f_body = gmsh.model.mesh.field.add("Distance")
            gmsh.model.mesh.field.setNumbers(f_body, "SurfacesList", robot_faces)
            gmsh.model.mesh.field.setNumber(f_body, "Sampling", 60)
            fields.append(_threshold(gmsh, f_body, size * s, far * s, grading))
            if low_curves:
                f_gap = gmsh.model.mesh.field.add("Distance")
                gmsh.model.mesh.field.setNumbers(f_gap, "CurvesList", low_curves)
                gmsh.model.mesh.field.setNumber(f_gap, "Sampling", 200)
                fields.append(_threshold(gmsh, f_gap, gap * s, far * s, grading))
        else:
            f_const = gmsh.model.mesh.field.add("MathEval")
            gmsh.model.mesh.field.setString(f_const, "F", repr(far * s))
            fields.append(f_const)
        f_min = gmsh.model.mesh.field.add("Min")
        gmsh.model.mesh.field.setNumbers(f_min, "FieldsList", fields)
        gmsh.model.mesh.field.setAsBackgroundMesh(f_min)
        for opt, val in (("Mesh.MeshSizeExtendFromBoundary", 0), ("Mesh.MeshSizeFromPoints", 0),
                         ("Mesh.MeshSizeFromCurvature", 0), ("Mesh.Algorithm", 6), ("Mesh.Algorithm3D", 1),
                         ("Mesh.Optimize", 1), ("General.NumThreads", 1)):
            gmsh.option.setNumber(opt, val)
        gmsh.model.mesh.generate(3)
        mesh = _gmsh_to_skfem(gmsh, skfem)
    finally:
        gmsh.finalize()
    facets = classify_facets(mesh, ((x0, x1), (y0, y1), (z0, z1)), tol=1e-9)
    return TetMesh(mesh, facets, time.perf_counter() - t0)


def _on_box_curve(gmsh, tag, bb) -> bool:
    """Whether curve ``tag`` lies in one of the box's planes (not on the robot)."""
    b = gmsh.model.getBoundingBox(1, tag)
    return any(abs(b[k] - bb[k]) < 1e-3 and abs(b[k + 3] - bb[k]) < 1e-3 for k in range(3)) or \
        any(abs(b[k] - bb[k + 3]) < 1e-3 and abs(b[k + 3] - bb[k + 3]) < 1e-3 for k in range(3))


def _threshold(gmsh, dist_field: int, size_min: float, size_max: float, grading: float) -> int:
    f = gmsh.model.mesh.field.add("Threshold")
    gmsh.model.mesh.field.setNumber(f, "InField", dist_field)
    gmsh.model.mesh.field.setNumber(f, "SizeMin", size_min)
    gmsh.model.mesh.field.setNumber(f, "SizeMax", size_max)
    gmsh.model.mesh.field.setNumber(f, "DistMin", 0.0)
    gmsh.model.mesh.field.setNumber(f, "DistMax", (size_max - size_min) / grading)
    return f


# --- the Stokes solve ----------------------------------------------------------------------
COMPONENTS = ("u^1", "u^2", "u^3")


@dataclass
class StokesSolution:
    """A Taylor–Hood P2–P1 Stokes solution.

    Attributes
    ----------
    u : ndarray (Nu,)
        Velocity coefficients of ``ubasis`` [m/s].
    p : ndarray (Np,)
        Pressure coefficients of ``pbasis`` [Pa].
    ubasis, pbasis : skfem bases
    reaction : ndarray (Nu,)
        ``K x`` on the velocity rows: the boundary traction tested with each basis function
        (``∫ σ n · φ_i`` over the boundary, ``n`` out of the fluid) [N].
    dofs : int
        Unknowns of the saddle-point system before constraints.
    solver : str
        ``"direct"`` or ``"minres"`` (with its iteration count).
    solve_time : float
        Seconds for assembly and solve.
    peak_memory : float
        Peak resident memory of the process after the solve [bytes] (``getrusage``; includes
        everything the process held before).
    """

    u: np.ndarray
    p: np.ndarray
    ubasis: object
    pbasis: object
    reaction: np.ndarray
    dofs: int
    solver: str
    solve_time: float
    peak_memory: float

    def force(self, mesh: TetMesh, name: str = "body") -> np.ndarray:
        """Force of the fluid on the boundary ``name`` ``(3,)`` [N] (minus the summed reactions there)."""
        dofs = self.ubasis.get_dofs(mesh.facets[name])
        return np.array([-self.reaction[dofs.all([c])].sum() for c in COMPONENTS])

    def velocity(self, points: np.ndarray) -> np.ndarray:
        """Velocity ``(P, 3)`` at points ``(P, 3)`` inside the mesh (NaN where a point is not found)."""
        return evaluate(self.ubasis, self.u, points)


def _locate(mesh, points: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """Index of a tetrahedron containing each point ``(P, 3)``, or -1 (barycentric test on near neighbours)."""
    from scipy.spatial import cKDTree

    cache = getattr(mesh, "_magctl_locator", None)
    if cache is None:
        v = mesh.p[:, mesh.t].transpose(2, 0, 1)                 # (T, 3 coords, 4 vertices)
        jac = v[:, :, 1:] - v[:, :, :1]
        cache = (cKDTree(v.mean(axis=2)), v[:, :, 0], np.linalg.inv(jac))
        mesh._magctl_locator = cache
    tree, v0, jinv = cache
    found = np.full(len(points), -1, dtype=np.int64)
    todo = np.arange(len(points))
    for k in (16, 64, 256):
        if len(todo) == 0:
            break
        k = min(k, len(v0))
        _, cand = tree.query(points[todo], k)
        cand = cand.reshape(len(todo), k)
        lam = np.einsum("pkij,pkj->pki", jinv[cand], points[todo, None, :] - v0[cand])
        bary = np.concatenate([1.0 - lam.sum(axis=-1, keepdims=True), lam], axis=-1).min(axis=-1)
        best = bary.argmax(axis=1)
        ok = bary[np.arange(len(todo)), best] >= -tol
        found[todo[ok]] = cand[np.arange(len(todo)), best][ok]
        todo = todo[~ok]
    return found


def evaluate(basis, coeffs: np.ndarray, points: np.ndarray) -> np.ndarray:
    """A finite-element field at points ``(P, 3)``: ``(P, 3)`` for a vector basis, ``(P,)`` for a scalar one.

    Points outside the mesh give NaN. Same evaluation as ``skfem``'s ``CellBasis.probes`` (reference-element
    basis at the mapped points), with a point location that tolerates points on the boundary.
    """
    from skfem import ElementVector

    points = np.asarray(points, float).reshape(-1, 3)
    comp = 3 if isinstance(basis.elem, ElementVector) else 1
    out = np.full((comp, len(points)), np.nan)
    cells = _locate(basis.mesh, points)
    ok = cells >= 0
    if ok.any():
        x, c = points[ok].T, cells[ok]
        ref = basis.mapping.invF(x[:, :, None], tind=c)
        vals = np.zeros((comp, ok.sum()))
        for k in range(basis.Nbfun):
            phi = np.asarray(basis.elem.gbasis(basis.mapping, ref, k, tind=c)[0])
            vals += phi.reshape(comp, -1) * coeffs[basis.element_dofs[k, c]]
        out[:, ok] = vals
    return out.T if comp == 3 else out[0]


def solve_stokes(mesh: TetMesh, viscosity: float, dirichlet, pin_pressure: bool, solver: str = "auto",
                 direct_limit: int = 40_000, rtol: float = 1e-9, maxiter: int = 3000) -> StokesSolution:
    """Taylor–Hood P2–P1 Stokes flow ``−div σ = 0``, ``div u = 0``, ``σ = −p I + 2μ ε(u)``.

    Parameters
    ----------
    mesh : TetMesh
    viscosity : float
        μ [Pa·s].
    dirichlet : iterable of ``(face, {component: value})``
        Prescribed velocity components (0, 1, 2 for x, y, z) [m/s] on the facets ``mesh.facets[face]``;
        a value is a number or a function of the coordinates ``(3, n)`` of the degrees of freedom.
        Components not prescribed on a boundary have zero traction there (natural condition of
        the symmetric-gradient form): a face with only the normal component prescribed is a slip
        (symmetry) face, a face with nothing prescribed is traction-free.
    pin_pressure : bool
        Fix one pressure value to 0 (needed when the normal velocity is prescribed on the whole
        boundary, which leaves the pressure defined up to a constant).
    solver : {"auto", "direct", "minres"}
        ``auto``: sparse direct (SuperLU) up to ``direct_limit`` unknowns, MINRES above.
    rtol, maxiter
        MINRES tolerance (relative preconditioned residual) and iteration cap.
    """
    skfem, _ = require_fem()
    from skfem import Basis, ElementTetP1, ElementTetP2, ElementVector, asm
    from skfem.models.elasticity import linear_elasticity
    from skfem.models.general import divergence
    from skfem.models.poisson import mass

    if not viscosity > 0:
        raise ParameterError(f"viscosity must be positive, got {viscosity!r} Pa*s")
    if solver not in ("auto", "direct", "minres"):
        raise ParameterError(f"solver must be 'auto', 'direct' or 'minres', got {solver!r}")
    t0 = time.perf_counter()
    ub = Basis(mesh.mesh, ElementVector(ElementTetP2()), intorder=2)
    pb = Basis(mesh.mesh, ElementTetP1(), intorder=2)
    a = asm(linear_elasticity(0.0, viscosity), ub).tocsr()        # 2μ ε(u):ε(v)
    b = asm(divergence, ub, pb).tocsr()                            # (div u, q)
    nu, npr = ub.N, pb.N
    k = sp.bmat([[a, -b.T], [-b, None]], format="csr")
    x = np.zeros(nu + npr)
    fixed = np.zeros(nu + npr, bool)
    for face, comps in dirichlet:
        if face not in mesh.facets:
            raise ParameterError(f"no boundary named {face!r}; known: {', '.join(mesh.facets)}")
        dofs = ub.get_dofs(mesh.facets[face])
        for c, val in comps.items():
            idx = dofs.all([COMPONENTS[c]])
            x[idx] = val(ub.doflocs[:, idx]) if callable(val) else val
            fixed[idx] = True
    if pin_pressure:
        fixed[nu] = True
    free = np.nonzero(~fixed)[0]
    rhs = -(k @ x)[free]
    kii = k[free][:, free].tocsc()
    use_direct = solver == "direct" or (solver == "auto" and len(free) <= direct_limit)
    # symmetric diagonal scaling: velocity rows by 1/sqrt(μℓ), pressure rows by sqrt(μℓ)/ℓ², so both
    # blocks are O(1) in SI units (ℓ the mean element size); the solution is unscaled afterwards
    ell = float(np.cbrt(np.mean(_volumes(mesh.mesh))))
    du = 1.0 / math.sqrt(viscosity * ell)
    scale = np.where(free < nu, du, 1.0 / (du * ell**2))
    d = sp.diags(scale)
    kii = (d @ kii @ d).tocsc()
    if use_direct:
        y = spla.splu(kii, permc_spec="COLAMD").solve(rhs * scale)
        how = "direct"
    else:
        y, how = _minres(kii, rhs * scale, free, nu, pb, viscosity * du**2 * ell**4, mass, asm, rtol, maxiter)
    x[free] = y * scale
    reaction = k[:nu] @ x
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024.0
    return StokesSolution(x[:nu], x[nu:], ub, pb, reaction, nu + npr, how, time.perf_counter() - t0, float(peak))


def _volumes(mesh) -> np.ndarray:
    """Volumes of the tetrahedra of ``mesh`` [m³]."""
    v = mesh.p[:, mesh.t]
    return np.abs(np.linalg.det((v[:, 1:] - v[:, :1]).transpose(2, 0, 1))) / 6.0


def _minres(kii, rhs, free, nu, pb, pressure_scale, mass, asm, rtol, maxiter):
    """MINRES with the block-diagonal preconditioner diag(AMG(A), c M_p⁻¹) (Elman, Silvester & Wathen §4.2);
    ``c`` is μ times the system's pressure scaling, so the pressure block approximates the Schur complement."""
    vel = free < nu
    nv = int(vel.sum())
    a_ii = kii[:nv][:, :nv].tocsr()
    mp = np.asarray(asm(mass, pb).sum(axis=1)).ravel()                   # lumped pressure mass
    mp_free = mp[free[~vel] - nu]
    try:
        import pyamg

        ml = pyamg.smoothed_aggregation_solver(a_ii, symmetry="symmetric", max_coarse=2000)
        amg = ml.aspreconditioner(cycle="V")
        apply_a, label = amg.matvec, "minres+amg"
    except ImportError:
        ilu = spla.spilu(a_ii.tocsc(), drop_tol=1e-4, fill_factor=10)
        apply_a, label = ilu.solve, "minres+ilu"

    def prec(v):
        out = np.empty_like(v)
        out[:nv] = apply_a(v[:nv])
        out[nv:] = pressure_scale * v[nv:] / mp_free
        return out

    m = spla.LinearOperator(kii.shape, prec)
    count = [0]

    def cb(_):
        count[0] += 1

    sol, info = spla.minres(kii, rhs, M=m, rtol=rtol, maxiter=maxiter, callback=cb)
    res = float(np.linalg.norm(kii @ sol - rhs) / np.linalg.norm(rhs))
    if info != 0 or res > 1e-6:
        raise MagctlError(f"MINRES stopped after {count[0]} iterations (info {info}) at relative residual {res:.1e}")
    return sol, f"{label} ({count[0]} it, residual {res:.0e})"


# --- the paper's box ---------------------------------------------------------------------
OUTLETS = ("velocity", "traction")


def box_conditions(motion: str, outlet: str = "velocity") -> tuple[list, bool]:
    """Boundary conditions of the box for unit robot motion, in the robot frame (paper §IV-C).

    ``motion="x"`` (the paper's case): the oil streams past the held robot at ``(−1, 0, 0)``. Inlet
    (front face ``x_max``) and ground (``z_min``) at ``(−1, 0, 0)``; the outlet (rear face ``x_min``)
    either at the same prescribed velocity (``outlet="velocity"``: the paper's "flow of 0.4 mm/s" on
    both faces) or traction-free (``"traction"``); symmetry faces ``y_min`` (the mirror plane),
    ``y_max`` and ``z_max`` with zero normal velocity and free slip; the robot no-slip.

    ``motion="y"``: the same construction with the inlet on the side face ``y_max`` at ``(0, −1, 0)``
    and the ground moving with it; the faces ``x_min``/``x_max`` and ``z_max`` are symmetry faces; on
    the mirror plane ``y_min`` the flow of a sideways motion is odd (``u_x = u_z = 0``, zero normal
    traction), which replaces the outlet of the other half.

    Returns the Dirichlet list of :func:`solve_stokes` and whether the pressure needs pinning.
    """
    if outlet not in OUTLETS:
        raise ParameterError(f"outlet must be one of {', '.join(OUTLETS)}, got {outlet!r}")
    still = {0: 0.0, 1: 0.0, 2: 0.0}
    if motion == "x":
        stream = {0: -1.0, 1: 0.0, 2: 0.0}
        bcs = [("y_min", {1: 0.0}), ("y_max", {1: 0.0}), ("z_max", {2: 0.0}), ("x_max", stream),
               ("z_min", stream), ("body", still)]
        if outlet == "velocity":
            bcs.append(("x_min", stream))
        return bcs, outlet == "velocity"
    if motion == "y":
        stream = {0: 0.0, 1: -1.0, 2: 0.0}
        bcs = [("x_min", {0: 0.0}), ("x_max", {0: 0.0}), ("z_max", {2: 0.0}), ("y_min", {0: 0.0, 2: 0.0}),
               ("y_max", stream), ("z_min", stream), ("body", still)]
        return bcs, False
    raise ParameterError(f"motion must be 'x' or 'y', got {motion!r}")


def box_solve(geometry: RobotGeometry, viscosity: float, domain: Domain, spec: MeshSpec = MeshSpec(),
              motion: str = "x", outlet: str = "velocity", robot_x: float = 0.0, mesh: TetMesh | None = None,
              solver: str = "auto") -> tuple[StokesSolution, TetMesh]:
    """Robot-frame Stokes flow in the box for unit robot speed along body ``motion`` (see :func:`box_conditions`).

    The lab-frame flow of a robot moving at +1 along ``motion`` in still oil is this velocity plus the
    unit vector of ``motion`` (the paper's final subtraction of the free-stream velocity).
    """
    mesh = mesh if mesh is not None else box_mesh(geometry, domain, spec, robot_x)
    bcs, pin = box_conditions(motion, outlet)
    return solve_stokes(mesh, viscosity, bcs, pin, solver=solver), mesh


def _cache_dir() -> Path:
    root = os.environ.get("MAGCTL_CACHE")
    return Path(root) if root else Path.home() / ".cache" / "magctl"


def _cache_key(*parts) -> str:
    h = hashlib.sha256()
    for part in parts:
        if isinstance(part, np.ndarray):
            h.update(np.ascontiguousarray(part, dtype=float).tobytes())
        elif isinstance(part, bytes):
            h.update(part)
        else:
            h.update(repr(part).encode())
        h.update(b"|")
    return h.hexdigest()[:24]


def map_key(geometry: RobotGeometry, viscosity: float, height: float, domain: Domain, gx, gy, spec: MeshSpec,
            robot_x: float, outlet: str) -> str:
    """Hash of every input of a box map (and :data:`CACHE_VERSION`): the name of its cache file."""
    return _cache_key(CACHE_VERSION, geometry.key(), round(float(viscosity), 15), round(float(height), 12),
                      domain.key(), np.asarray(gx, float), np.asarray(gy, float),
                      tuple(round(v, 12) for v in spec.resolved(geometry)),
                      round(float(robot_x), 12), outlet)


def box_flow_solution(geometry: RobotGeometry, viscosity: float, height: float, domain: Domain, gx, gy,
                      mesh_size: float | MeshSpec = 30e-6, robot_x: float = 0.0, outlet: str = "velocity",
                      solver: str = "auto", cache: bool = True) -> tuple[np.ndarray, np.ndarray, dict]:
    """:func:`box_flow_maps` with its run record: ``(maps, inside, info)``.

    ``info`` holds the mesh (tetrahedra), unknowns, mesh and solve times, peak memory, the solver,
    and the drag on the robot ``(2, 3)`` [N per m/s] for the two unit motions (whole robot). Results
    are cached on disk (``$MAGCTL_CACHE`` or ``~/.cache/magctl``, ``fem_box_<hash>.npz``), keyed by
    every input; ``info["cached"]`` says whether this call read the cache.
    """
    spec = mesh_size if isinstance(mesh_size, MeshSpec) else MeshSpec(float(mesh_size))
    resolved = spec.resolved(geometry)
    require_fem()
    gx, gy = np.asarray(gx, float), np.asarray(gy, float)
    if gx.ndim != 1 or gy.ndim != 1 or len(gx) < 2 or len(gy) < 2 or np.any(np.diff(gx) <= 0) \
            or np.any(np.diff(gy) <= 0):
        raise ParameterError("map grids gx, gy must be increasing 1-D arrays of at least two nodes")
    if not (viscosity > 0 and height > 0):
        raise ParameterError(f"viscosity ({viscosity!r} Pa*s) and map height ({height!r} m) must be positive")
    (x0, x1), (_, w), (_, h) = _box_bounds(domain, robot_x)
    if height >= h:
        raise ParameterError(f"map height {height!r} m is above the box top {h!r} m")
    if outlet not in OUTLETS:
        raise ParameterError(f"outlet must be one of {', '.join(OUTLETS)}, got {outlet!r}")
    path = _cache_dir() / f"fem_box_{map_key(geometry, viscosity, height, domain, gx, gy, spec, robot_x, outlet)}.npz"
    if cache and path.exists():
        with np.load(path) as z:
            info = json.loads(str(z["info"]))
            info["cached"] = True
            return z["maps"], z["inside"], info
    mesh = box_mesh(geometry, domain, spec, robot_x)
    xx, yy = np.meshgrid(gx, gy)
    pts = np.column_stack([xx.ravel(), np.abs(yy.ravel()), np.full(xx.size, float(height))])
    in_box = (pts[:, 0] >= x0) & (pts[:, 0] <= x1) & (pts[:, 1] <= w)
    in_robot = geometry.contains(pts)
    fluid = in_box & ~in_robot
    maps = np.zeros((2, len(pts), 3))
    drag = np.zeros((2, 3))
    runs = []
    for k, motion in enumerate(("x", "y")):
        sol, _ = box_solve(geometry, viscosity, domain, spec, motion, outlet, robot_x, mesh, solver)
        u = sol.velocity(pts[fluid])
        if np.isnan(u).any():
            raise MagctlError(f"{int(np.isnan(u).any(axis=1).sum())} map points in the oil were not found in the mesh")
        maps[k, fluid] = u + np.eye(3)[k]              # robot frame → lab frame (paper §IV-C)
        maps[k, in_robot & in_box] = np.eye(3)[k]     # rigid motion inside the robot
        f = sol.force(mesh)
        drag[k] = 2 * f * (np.array([1.0, 0.0, 1.0]) if motion == "x" else np.array([0.0, 1.0, 0.0]))
        runs.append({"motion": motion, "dofs": int(sol.dofs), "solver": sol.solver, "solve_time_s": sol.solve_time,
                     "peak_memory_bytes": sol.peak_memory})
    # mirror image for y < 0: x-motion flow has u_x, u_z even and u_y odd in y; y-motion the reverse
    lower = (yy.ravel() < 0)
    parity = np.array([[1.0, -1.0, 1.0], [-1.0, 1.0, -1.0]])
    maps[:, lower] *= parity[:, None, :]
    maps = maps.reshape(2, len(gy), len(gx), 3)
    inside = (in_robot & in_box).reshape(len(gy), len(gx))
    info = {"tets": mesh.n_tets, "vertices": int(mesh.mesh.p.shape[1]), "mesh_time_s": mesh.mesh_time,
            "runs": runs, "drag": drag.tolist(), "mesh_spec": list(resolved), "robot_x": float(robot_x),
            "outlet": outlet, "domain": list(domain.key())}
    if cache:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp.npz")
        np.savez_compressed(tmp, maps=maps, inside=inside, info=json.dumps(info))
        os.replace(tmp, path)
    info["cached"] = False
    return maps, inside, info


def box_flow_maps(geometry: RobotGeometry, viscosity: float, height: float, domain: Domain, gx, gy,
                  mesh_size: float | MeshSpec = 30e-6, robot_x: float = 0.0, outlet: str = "velocity",
                  solver: str = "auto", cache: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Lab-frame flow per unit robot speed on the robot-frame grid ``gx × gy`` at ``height`` (paper §IV-C box).

    Returns ``maps (2, ny, nx, 3)`` — index 0 for unit motion along body x, 1 along body y, in the
    layout of :attr:`magctl.plant.fluid.flow.RobotFlow.maps` — and ``inside (ny, nx)``, the grid nodes
    inside the robot (flow there is the rigid motion). Nodes outside the box get zero flow: in this
    model there is no oil beyond it. Nodes with ``y < 0`` are the mirror images of the solved half.

    Parameters
    ----------
    geometry : RobotGeometry
    viscosity : float
        μ [Pa·s] (the flow for a prescribed robot speed does not depend on it; the drag does).
    height : float
        Map plane above the glass [m] (the sphere centre, R + ε).
    domain : Domain
        ``kind="box"``: ``box_length`` L along x, ``box_half_width`` W, ``depth`` H [m].
    gx, gy : array
        Increasing grid nodes [m].
    mesh_size : float or MeshSpec
        Element size on the robot [m], or the full :class:`MeshSpec`.
    robot_x : float
        Robot reference point ahead of the box centre along x [m].
    outlet : {"velocity", "traction"}
        Rear face condition (:func:`box_conditions`).
    """
    maps, inside, _ = box_flow_solution(geometry, viscosity, height, domain, gx, gy, mesh_size, robot_x, outlet,
                                        solver, cache)
    return maps, inside


def map_axis(half: float, fine_half: float = 0.6e-3, fine_step: float = 15e-6, growth: float = 1.25) -> np.ndarray:
    """Symmetric grid nodes: ``fine_step`` within ``±fine_half``, then steps growing by ``growth`` to ``±half``
    (the layout of the boundary-element maps)."""
    nodes = list(np.arange(0.0, min(fine_half, half) + fine_step / 2, fine_step))
    step = fine_step
    while nodes[-1] < half:
        step *= growth
        nodes.append(min(nodes[-1] + step, half))
    pos = np.asarray(nodes)
    return np.concatenate([-pos[:0:-1], pos])


@dataclass
class BoxFlow(RobotFlow):
    """The box model's maps behind :class:`~magctl.plant.fluid.flow.RobotFlow`'s look-up interface.

    Built by :meth:`build` (never by the Stokeslet solve of ``RobotFlow``): ``maps``/``inside`` come from
    :func:`box_flow_maps`, there are no Stokeslets (``points`` ``(0, 3)``, ``forces`` ``(2, 0, 3)``) and
    :meth:`velocity_exact` is zero, so points off the map — which covers the whole box — get no flow,
    as outside the box there is no oil. Pass it to :class:`magctl.plant.sphere.Spheres` as ``flow=``.
    """

    domain: Domain = field(default_factory=Domain)
    info: dict = field(default_factory=dict, repr=False)

    @classmethod
    def build(cls, geometry: RobotGeometry | None = None, viscosity: float | None = None,
              height: float | None = None, domain: Domain | None = None, mesh_size: float | MeshSpec = 30e-6,
              robot_x: float = 0.0, outlet: str = "velocity", fine_step: float = 15e-6, solver: str = "auto",
              cache: bool = True) -> BoxFlow:
        """Solve (or read from the cache) the box and wrap its maps.

        Defaults: ``models/robot_geometry.toml``, ``models/fluid.toml`` (μ = ν ρ and ``[domain]``, which
        must then be a box), and the sphere-centre height R + ε of ``models/sphere.toml``. The grid has
        ``fine_step`` spacing within ±0.6 mm and covers the box with one node beyond it on every side.
        """
        geometry, viscosity, height, domain = flow_defaults(geometry, viscosity, height, domain)
        (x0, x1), (_, w), _ = _box_bounds(domain, robot_x)
        half = max(abs(x0), abs(x1), w)
        g = map_axis(half, fine_step=fine_step)
        g = np.concatenate([[g[0] - fine_step], g, [g[-1] + fine_step]])   # one node outside the box
        maps, inside, info = box_flow_solution(geometry, viscosity, float(height), domain, g, g, mesh_size,
                                               robot_x, outlet, solver, cache)
        flow = object.__new__(cls)
        flow.geometry, flow.viscosity, flow.height = geometry, viscosity, float(height)
        flow.map_half, flow.map_step = float(g[-1]), float(fine_step)
        flow.points, flow.forces, flow.eps = np.zeros((0, 3)), np.zeros((2, 0, 3)), 0.0
        flow.gx, flow.gy, flow.maps, flow.inside = g, g.copy(), maps, inside
        flow.domain, flow.info = domain, info
        return flow

    def velocity_exact(self, pts: np.ndarray) -> np.ndarray:
        """Zero ``(2, P, 3)``: the map covers the box, and beyond it there is no oil."""
        return np.zeros((2, len(pts), 3))

    def drag(self) -> np.ndarray:
        """Hydrodynamic force on the whole robot ``(2, 3)`` [N per m/s] from the finite-element reactions."""
        return np.asarray(self.info["drag"], float)
