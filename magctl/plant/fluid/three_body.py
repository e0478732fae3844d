"""The robot, a sphere and the glass in one Stokes problem (docs/fluid.md §5, "The three-body check").

The plant moves a sphere by the flow the robot makes *without* the sphere (:mod:`magctl.plant.fluid.flow`,
eq 4) plus the robot–sphere lubrication (:mod:`magctl.plant.fluid.lubrication`). This module solves the
problem those two pieces approximate: the robot translating along its body x axis, the sphere free of
force and torque, both above the no-slip glass (Blake's tensor, :mod:`magctl.plant.fluid.bem`), with
the sphere on the robot's symmetry plane in front of its notch, so the mirror ``y → −y`` halves the
system. Both surfaces are graded towards the narrowest gaps: a robot panel is split (flat triangles,
exact) until its edge is at most ``beta`` × its distance to the sphere, a sphere panel until its edge is
at most ``beta`` × its distance to the glass or the robot, neither below ``size_min``.

The sphere's rigid motion ``(V_x, V_z, aΩ_y)`` follows from four resistance solves on one factorisation
(robot moving, sphere held; sphere translating along x, along z; sphere rotating) and the force- and
torque-free balance of the sphere.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.spatial

from magctl.plant.fluid import bem
from magctl.plant.fluid.geometry import RobotGeometry
from magctl.plant.fluid.lubrication import edge_curvatures, film_area, film_laws, film_resistance
from magctl.plant.fluid.wall_drag import accurate_coefficients, accurate_mobility, normal_resistance

MAX_SPLITS = 14
"""Largest number of refinement rounds of a surface (each halves the panels it splits)."""


def _split_flat(t: np.ndarray) -> np.ndarray:
    """Each triangle into four by its edge midpoints (flat panels stay on their plane)."""
    m01, m12, m20 = (t[:, 0] + t[:, 1]) / 2, (t[:, 1] + t[:, 2]) / 2, (t[:, 2] + t[:, 0]) / 2
    return np.concatenate([np.stack([t[:, 0], m01, m20], 1), np.stack([m01, t[:, 1], m12], 1),
                           np.stack([m20, m12, t[:, 2]], 1), np.stack([m01, m12, m20], 1)])


def _longest_edge(t: np.ndarray) -> np.ndarray:
    return np.max(np.linalg.norm(t - np.roll(t, 1, axis=1), axis=2), axis=1)


def _sample(t: np.ndarray) -> np.ndarray:
    """Vertices, edge midpoints and centroid of each triangle ``(T, 7, 3)`` (where a size field is probed)."""
    mids = (t + np.roll(t, 1, axis=1)) / 2
    return np.concatenate([t, mids, t.mean(axis=1, keepdims=True)], axis=1)


def refine(tris: np.ndarray, size, split=_split_flat) -> np.ndarray:
    """Split triangles until each one's longest edge is at most ``size(points)`` at its vertices, edge
    midpoints and centroid (``size`` maps ``(N, 3)`` points to ``(N,)`` lengths)."""
    done = []
    t = np.asarray(tris, float)
    for _ in range(MAX_SPLITS):
        pts = _sample(t)
        need = size(pts.reshape(-1, 3)).reshape(len(t), -1).min(axis=1)
        big = _longest_edge(t) > need
        done.append(t[~big])
        if not big.any():
            return np.concatenate(done)
        t = split(t[big])
    raise ValueError(f"surface refinement did not finish in {MAX_SPLITS} rounds (a size field of zero?)")


def octahedron_half() -> np.ndarray:
    """The four faces ``(4, 3, 3)`` of the unit octahedron on the ``y ≥ 0`` side, outward normals (the seed of
    a sphere mesh: no face crosses ``y = 0``, so the mirror ``y → −y`` completes it)."""
    e = np.eye(3)
    faces = []
    for sx in (1, -1):
        for sz in (1, -1):
            tri = np.array([e[0] * sx, e[1], e[2] * sz])
            if np.dot(np.cross(tri[1] - tri[0], tri[2] - tri[0]), tri.sum(0)) < 0:
                tri = tri[[0, 2, 1]]
            faces.append(tri)
    return np.array(faces)


def sphere_half(centre, radius: float, size) -> np.ndarray:
    """The ``y ≥ 0`` half of a sphere (outward normals) refined by ``size`` from an octahedron, its new
    vertices projected onto the sphere; ``centre`` must lie on ``y = 0``."""
    centre = np.asarray(centre, float)
    unit = octahedron_half()

    def split(t):
        s = _split_flat(t)
        return s / np.linalg.norm(s, axis=2, keepdims=True)

    return centre + radius * refine(unit, lambda p: size(centre + radius * p) / radius, split)


@dataclass(frozen=True)
class Mesh:
    """Grading of the three-body surfaces: panel edge ``≤ beta × distance`` to the nearest other surface,
    between ``size_min`` and ``size_max`` (sphere) [m]."""

    beta: float = 0.5
    size_min: float = 1.5e-6
    size_max: float = 25e-6

    def scaled(self, factor: float) -> Mesh:
        return Mesh(self.beta * factor, self.size_min * factor, self.size_max * factor)


@dataclass(frozen=True)
class Response:
    """The free sphere's motion for the robot translating at unit speed along its body x axis.

    Attributes
    ----------
    velocity : ndarray (3,)
        ``(V_x, V_z, aΩ_y)`` of the force- and torque-free sphere [m/s per m/s].
    flow : ndarray (3,)
        The robot-only flow at the sphere's centre (the sphere absent) [m/s per m/s].
    gap_robot : float
        Shortest distance between the sphere's surface and the robot's [m] (3-D, from the panels).
    panels : int
        Panels in the solve (both mirror halves).
    centre : ndarray (3,)
        The sphere's centre [m].
    load : ndarray (4, 3)
        Force ``(F_x, F_z, T_y/a)`` the sphere exerts on the fluid [N per m/s] for the robot moving (sphere
        held), and for the sphere translating along x, along z and rotating (``aΩ_y``) at unit speed.
    """

    velocity: np.ndarray
    flow: np.ndarray
    gap_robot: float
    panels: int
    centre: np.ndarray
    load: np.ndarray


def _robot_distance(robot: np.ndarray):
    """Distance to the robot's surface (both halves) from points, through a k-d tree of its panels' samples."""
    pts = _sample(np.concatenate([robot, bem.mirrored(robot, 1)])).reshape(-1, 3)
    tree = scipy.spatial.cKDTree(pts)
    return lambda p: tree.query(p)[0]


def solve_response(geometry: RobotGeometry, centre, radius: float, viscosity: float, mesh: Mesh = Mesh()
                   ) -> Response:
    """Solve the robot–sphere–glass problem with the sphere's centre at ``centre = (x, 0, z)`` (robot frame)."""
    centre = np.asarray(centre, float)
    if abs(centre[1]) > 0 or centre[2] <= radius:
        raise ValueError(f"sphere centre {centre.tolist()} must lie on y = 0 and above the glass (z > radius)")
    base = geometry.surface_mesh()
    if np.any(np.linalg.norm(_sample(base).reshape(-1, 3) - centre, axis=1) < radius):
        raise ValueError(f"the sphere at {centre.tolist()} overlaps the robot")

    def robot_size(p):
        d = np.linalg.norm(p - centre, axis=1) - radius
        return np.maximum(mesh.beta * d, mesh.size_min)

    robot = refine(base, robot_size)
    to_robot = _robot_distance(robot)

    def sphere_size(p):
        d = np.minimum(p[:, 2], to_robot(p))
        return np.clip(mesh.beta * d, mesh.size_min, mesh.size_max)

    sphere = sphere_half(centre, radius, sphere_size)
    gap_robot = float(to_robot(_sample(sphere).reshape(-1, 3)).min())
    body = np.concatenate([np.zeros(len(robot), np.int64), np.ones(len(sphere), np.int64)])
    even, _ = bem.y_symmetric(np.concatenate([robot, sphere]), body)
    n, nr = even.n_independent, len(robot)
    x = bem.centroids(even.tris[:n])
    rel = x[nr:] - centre
    rhs = np.zeros((4, n, 3))
    rhs[0, :nr, 0] = 1.0                                             # robot along x, sphere held
    rhs[1, nr:, 0] = 1.0                                             # sphere along x
    rhs[2, nr:, 2] = 1.0                                             # sphere along z
    rhs[3, nr:, 0] = rel[:, 2] / radius                              # sphere rotating: aΩ_y = 1
    rhs[3, nr:, 2] = -rel[:, 0] / radius
    q = bem.solve(even, rhs, viscosity, deflate=True)
    on_sphere = np.concatenate([body, body]) == 1
    f = q[:, on_sphere] * bem.areas(even.tris[on_sphere])[None, :, None]
    r = bem.centroids(even.tris[on_sphere]) - centre
    force = f.sum(axis=1)                                            # on the fluid, (4, 3)
    torque_y = (r[None, :, 2] * f[..., 0] - r[None, :, 0] * f[..., 2]).sum(axis=1) / radius
    load = np.column_stack([force[:, 0], force[:, 2], torque_y])     # (4, 3): Fx, Fz, T_y/a
    velocity = np.linalg.solve(load[1:].T, -load[0])

    flow = robot_only_flow(geometry, viscosity, centre[None])[0]
    return Response(velocity, flow, gap_robot, 2 * n, centre, load)


_ROBOT_ONLY: dict = {}


def robot_only_flow(geometry: RobotGeometry, viscosity: float, points: np.ndarray) -> np.ndarray:
    """Flow ``(P, 3)`` at ``points`` of the robot alone translating at unit speed along its body x axis
    (the solve is kept per geometry and viscosity for the process)."""
    key = (geometry.key(), viscosity)
    if key not in _ROBOT_ONLY:
        robot_only, _ = bem.y_symmetric(geometry.surface_mesh())
        rhs = np.zeros((1, robot_only.n_independent, 3))
        rhs[0, :, 0] = 1.0
        _ROBOT_ONLY[key] = robot_only.tris, bem.solve(robot_only, rhs, viscosity, deflate=True)
    tris, q = _ROBOT_ONLY[key]
    return bem.layer_velocity(points, tris, q, viscosity)[0]


def wall_resistance(radius: float, gap, viscosity: float) -> np.ndarray:
    """Exact resistance ``(3, 3)`` of a lone sphere at ``gap`` above the glass: the force ``(F_x, F_z, T_y/a)``
    it exerts on the fluid for unit ``(V_x, V_z, aΩ_y)`` [N per m/s], from Goldman, Cox & Brenner (1967a)
    ``f_t, f_r, t_t, t_r`` (force on the sphere ``6πμa(f_t V + f_r aΩ)``, torque ``8πμa²(t_t V + t_r aΩ)``,
    Ω about +y rolls the sphere towards +x) and Brenner's (1961) normal factor λ."""
    d = np.asarray(gap, float) / radius
    f_t, f_r, t_t, t_r, _, _ = accurate_coefficients(d)
    lam = normal_resistance(d)
    six, eight = 6 * np.pi * viscosity * radius, 8 * np.pi * viscosity * radius
    on_sphere = np.array([[six * f_t, 0.0, six * f_r], [0.0, -six * lam, 0.0], [eight * t_t, 0.0, eight * t_r]])
    return -on_sphere


def at_wall_gap(response: Response, geometry: RobotGeometry, radius: float, viscosity: float, gap: float
                ) -> np.ndarray:
    """The sphere's ``(V_x, V_z, aΩ_y)`` carried from the solved wall gap to a smaller ``gap`` that no mesh
    resolves, as Stokesian dynamics adds pair lubrication to a far-field resistance: the sphere's resistance
    changed by the lone sphere's exact change between the two gaps (:func:`wall_resistance`), and the robot's
    force on the held sphere scaled by the change of the robot-only flow at the centre (the sphere lowered
    to the new gap) times that of the lone sphere's force in a wall shear flow (``f_s``)."""
    solved = response.centre[2] - radius
    r_ss = response.load[1:].T + wall_resistance(radius, gap, viscosity) - wall_resistance(radius, solved, viscosity)
    lowered = response.centre.copy()
    lowered[2] = radius + gap
    u_new = robot_only_flow(geometry, viscosity, lowered[None])[0, 0]
    f_s_new, f_s_old = accurate_coefficients(gap / radius)[4], accurate_coefficients(solved / radius)[4]
    forcing = response.load[0] * (u_new * f_s_new) / (response.flow[0] * f_s_old)
    return np.linalg.solve(r_ss, -forcing)


@dataclass(frozen=True)
class Prediction:
    """What the plant's sphere block predicts for the same configuration (speeds over the robot's).

    Attributes
    ----------
    one_way : float
        ``V_x`` from the robot-only flow at the centre and the sphere's wall mobility (eq 4, accurate mode).
    face_film : float
        The same with the face film ``6πμA/h`` on the nearest edge, as if the sphere met a vertical face.
    with_film : float
        The same with the law the plant gives that edge (:func:`magctl.plant.fluid.lubrication.film_laws`).
    gap_footprint : float
        The lubrication gap: the centre's distance to the footprint outline less the radius [m].
    """

    one_way: float
    face_film: float
    with_film: float
    gap_footprint: float


def nearest_edge(point, polygon: np.ndarray) -> tuple[float, int]:
    """Distance from ``point (2,)`` to a closed polygon ``(V, 2)`` and the index of the nearest edge ``k → k+1``."""
    p0 = np.asarray(polygon, float)
    d = np.roll(p0, -1, axis=0) - p0
    t = np.clip(((point - p0) * d).sum(axis=1) / (d * d).sum(axis=1), 0.0, 1.0)
    dist = np.linalg.norm(point - (p0 + t[:, None] * d), axis=1)
    k = int(np.argmin(dist))
    return float(dist[k]), k


def notch_front(geometry: RobotGeometry) -> float:
    """x [m] where the footprint's front outline crosses the robot's axis ``y = 0`` (the notch's deepest point)."""
    v = geometry.footprint
    w = np.roll(v, -1, axis=0)
    cross = (v[:, 1] > 0) != (w[:, 1] > 0)
    x = v[cross, 0] + (w[cross, 0] - v[cross, 0]) * v[cross, 1] / (v[cross, 1] - w[cross, 1])
    return float(x.max())


def glide_resistance(gap_ratio: float) -> float:
    """``ζ/(6πμa)`` of a torque-free sphere translating along the glass at gap δ/a: ``|f_t − f_r t_t/t_r|``
    (Goldman, Cox & Brenner 1967a; the compiled form is :func:`magctl.plant.sphere_kernel.translation_resistance`)."""
    f_t, f_r, t_t, t_r, _, _ = accurate_coefficients(gap_ratio)
    return float(abs((f_t * t_r - f_r * t_t) / t_r))


def predict(geometry: RobotGeometry, centre, radius: float, flow_x: float, contact) -> Prediction:
    """The sphere block's ``V_x`` for a sphere on the robot's axis at ``centre`` in the robot-only flow
    ``flow_x`` (its wall gap ``z − a``): one-way (eq 4), and at the steady rate of
    :func:`magctl.plant.fluid.lubrication.film_gap` with a resistance ``R``: ``v = 1 + ζ(v₁ − 1)/(ζ + R)``.
    ``contact`` carries the laws' constants (:class:`magctl.plant.fluid.params.SphereParams`)."""
    centre = np.asarray(centre, float)
    gap = centre[2] - radius
    k = float(accurate_mobility(radius, gap, 0.0))
    one_way = k * flow_x
    footprint = geometry.footprint
    dist, edge = nearest_edge(centre[:2], footprint)
    h = dist - radius
    zeta = glide_resistance(gap / radius)
    h_f, h_e = contact.film_cutoff * radius, contact.edge_cutoff * radius
    area, log_coef = film_laws(geometry, radius, contact.edge_coefficient)
    face_area = film_area(radius, edge_curvatures(footprint))[edge]

    def speed(area_e, log_e):
        r = float(film_resistance(h, area_e, log_e, h_f, h_e)) / radius
        return 1.0 + zeta * (one_way - 1.0) / (zeta + r)

    return Prediction(one_way, speed(face_area, 0.0), speed(area[edge], log_coef[edge]), h)


def needed_resistance(v_three: float, v_one: float, zeta: float) -> float:
    """The lubrication resistance (in ``6πμa``) the plant's steady relation ``1 − v = ζ(1 − v₁)/(ζ + R)`` needs
    to give the three-body speed ``v_three`` from the one-way ``v_one``."""
    return float(zeta * ((1.0 - v_one) / (1.0 - v_three) - 1.0))
