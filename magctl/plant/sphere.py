"""The Spheres block: micro-spheres on the glass moved by the robot's Stokes flow and by contact.

Ports (docs/interfaces.md): inputs ``position`` (2,) m, ``heading`` () rad,
``velocity`` (2,) m/s of the robot; outputs ``spheres`` (N, 2) m and ``contact``
() bool (some sphere touched the robot during the last frame).

Within a frame the robot's velocity is held (zero-order hold) and its path is
split into sub-steps. Each sub-step

1. looks up the robot's flow at every sphere centre (:mod:`magctl.plant.fluid.flow`:
   map in the robot frame, scaled by the body-frame velocity, rotated back);
2. moves each sphere with the inertia-free near-wall balance F_G = 0 of eq 4
   (``V_p = k(δ) U``, :mod:`magctl.plant.fluid.wall_drag`), and its gap δ with the
   vertical balance of eq 8-9 (buoyant weight, drag, adhesion P within ε);
3. within a radius of the robot, replaces the sphere's velocity along the outline's normal by the one the
   lubrication between them gives (:mod:`magctl.plant.fluid.lubrication`: a face film where the sphere meets
   a face, the edge law fitted to the three-body solution where it meets an edge; the two-way coupling the
   robot-only flow map misses, ``accurate`` mode), closing to rough contact at ``contact_gap``;
4. enforces non-penetration against the robot's footprint (including the concave
   front face) and between spheres.

A frame is the block's kernel (:mod:`magctl.plant.sphere_kernel`, either drag mode), run by both
engines; the numpy array form it is tested against is ``RefSpheres`` in ``tests/reference/plant_blocks.py``.
:meth:`Spheres.sphere_velocity` evaluates the same flow and gap balance in numpy at given sphere states
(outside a frame).

Every sphere's mobility is scaled by the mean multiplier ``mobility`` (``models/sphere.toml``
``variability.mobility_ratio``, 1 by default; a rig's value is identified by :mod:`magctl.identify.side`).
Optional seeded per-trial variability (off by default, ``models/sphere.toml``):
a sphere may sit on a sticky patch that scales its mobility (§VI-B, "stuck on a
piece of dirt"), and a lognormal scatter of the mobility spreads the release
displacement (§VI-A). The inertial form of eq 6-8 is :func:`integrate_inertial`.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.integrate import solve_ivp

from magctl import FRAME_PERIOD_S
from magctl.core.block import Block, StateVar
from magctl.core.errors import ParameterError, WiringError
from magctl.core.ports import Port
from magctl.plant.fluid import params as fluid_params
from magctl.plant.fluid.domain import Domain
from magctl.plant.fluid.flow import RobotFlow, robot_flow
from magctl.plant.fluid.geometry import RobotGeometry
from magctl.plant.fluid.lubrication import edge_curvatures, film_area, film_laws
from magctl.plant.fluid.params import GRAVITY, SphereParams, fluid_viscosity, sphere_params
from magctl.plant.fluid.surface import pull_off_range
from magctl.plant.fluid.wall_drag import mobility, normal_factors, wall_table
from magctl.plant.outline import Polygon

InitialPositions = np.ndarray | Callable[[int, object], np.ndarray]


def _rot(theta):
    c, s = np.cos(theta), np.sin(theta)
    return c, s


def to_body(xy, origin, heading):
    """World points ``(B, N, 2)`` → robot frame given robot ``origin (B, 2)`` and ``heading (B,)``."""
    c, s = _rot(heading)
    d = xy - origin[:, None, :]
    return np.stack([c[:, None] * d[..., 0] + s[:, None] * d[..., 1],
                     -s[:, None] * d[..., 0] + c[:, None] * d[..., 1]], axis=-1)


def to_world(v, heading):
    """Rotate robot-frame vectors ``(B, N, 2)`` into the world frame."""
    c, s = _rot(heading)
    return np.stack([c[:, None] * v[..., 0] - s[:, None] * v[..., 1],
                     s[:, None] * v[..., 0] + c[:, None] * v[..., 1]], axis=-1)


def separate_spheres(xy: np.ndarray, radius: float, iterations: int = 3) -> np.ndarray:
    """Push overlapping spheres ``(B, N, 2)`` apart along their centre line, half each."""
    n = xy.shape[1]
    if n < 2:
        return xy
    i, j = np.triu_indices(n, 1)
    for _ in range(iterations):
        d = xy[:, j] - xy[:, i]
        dist = np.linalg.norm(d, axis=-1)
        overlap = 2 * radius - dist
        if not np.any(overlap > 0):
            break
        # centres closer than a picometre have no usable centre line: part them along x
        apart = dist > 1e-12
        unit = np.where(apart[..., None], d / np.where(apart, dist, 1.0)[..., None], (1.0, 0.0))
        corr = 0.5 * np.where(overlap > 0, overlap, 0.0)[..., None] * unit
        xy = xy.copy()
        np.add.at(xy, (slice(None), i), -corr)
        np.add.at(xy, (slice(None), j), corr)
    return xy


class Spheres(Block):
    """N micro-spheres on the glass, driven by the robot's flow and by contact.

    Parameters
    ----------
    initial_positions : array (N, 2) or (B, N, 2), or callable ``(batch, rng) -> (B, N, 2)``
        Sphere centres at step 0 [m].
    name : str
    params : SphereParams, optional
        ``models/sphere.toml`` by default.
    geometry : RobotGeometry, optional
        ``models/robot_geometry.toml`` by default.
    domain : Domain, optional
        What bounds the oil (``models/fluid.toml [domain]`` by default).
    viscosity, fluid_density : float, optional
        From ``models/fluid.toml`` by default.
    drag_mode : {"paper", "accurate"}, optional
        Overrides ``params.drag_mode``.
    roughness : float, optional
        Overrides the sphere–glass ε (``models/sphere.toml``, the measured 25 nm).
    lubrication : {"edges", "face", "none"}
        The robot–sphere lubrication in the accurate mode: ``edges`` (default) gives each footprint edge the
        law of where a resting sphere meets it (:func:`~magctl.plant.fluid.lubrication.film_laws`), ``face``
        the face film on every edge (the vertical-face model, a sensitivity case), ``none`` none (one-way flow).
    contact_gap : float, optional
        Overrides ``h_min``, the robot–sphere gap at rough contact where the lubrication ends
        (``models/sphere.toml [contact]``; docs/fluid.md §5).
    dt : float
        Frame period [s].
    flow : RobotFlow, optional
        The robot's flow to use instead of :func:`~magctl.plant.fluid.flow.robot_flow`'s (e.g. the
        finite-element box model, :class:`magctl.plant.fluid.fem_box.BoxFlow`); ``geometry``
        defaults to its geometry and must match it when given.
    """

    def __init__(self, initial_positions: InitialPositions, name: str = "spheres", *,
                 params: SphereParams | None = None, geometry: RobotGeometry | None = None,
                 domain: Domain | None = None,
                 viscosity: float | None = None, fluid_density: float | None = None,
                 drag_mode: str | None = None, roughness: float | None = None, contact_gap: float | None = None,
                 lubrication: str = "edges", dt: float = FRAME_PERIOD_S, flow: RobotFlow | None = None):
        self.params = params if params is not None else sphere_params()
        self.init = initial_positions
        n = self._count(initial_positions)
        super().__init__(name, inputs=[Port("position", (2,), "m"), Port("heading", (), "rad"),
                                       Port("velocity", (2,), "m/s")],
                         outputs=[Port("spheres", (n, 2), "m"), Port("contact", (), "1", "bool")],
                         dt=dt, feedthrough=False)
        self.n = n
        if flow is not None and geometry is not None and flow.geometry.key() != geometry.key():
            raise ParameterError("Spheres: the given flow was solved for another robot geometry than `geometry`")
        if geometry is None:
            geometry = flow.geometry if flow is not None else RobotGeometry.from_params()
        self.geometry = geometry
        self.domain = domain if domain is not None else Domain.from_params()
        self.viscosity = float(viscosity) if viscosity is not None else fluid_viscosity()
        rho_f = float(fluid_density) if fluid_density is not None else fluid_params.fluid_density()
        self.mode = drag_mode if drag_mode is not None else self.params.drag_mode
        if self.mode not in ("paper", "accurate"):
            raise ParameterError(f"drag_mode must be 'paper' or 'accurate', got {self.mode!r}")
        self.roughness = float(roughness) if roughness is not None else self.params.roughness
        if self.roughness <= 0:
            raise ParameterError(f"roughness must be positive, got {self.roughness!r} m")
        r = self.params.radius
        self.radius = r
        volume = 4.0 / 3.0 * np.pi * r**3
        self.buoyant_weight = (self.params.density - rho_f) * volume * GRAVITY       # W_b, eq 8
        self.pull_off = pull_off_range(r).p_min if self.params.adhesion else 0.0    # P, eq 3 (low end)
        self.zeta = 6 * np.pi * self.viscosity * r                                    # eq 9 drag coefficient
        self.footprint = self.geometry.footprint
        self._footprint = Polygon(self.footprint)
        self._box = np.abs(self.footprint).max(axis=0) + r
        self.reach = float(np.linalg.norm(self.footprint, axis=1).max()) + r
        self._flow: RobotFlow | None = flow
        self._k_contact = float(mobility(self.mode, r, 0.0, self.roughness))   # V_p/U resting on the glass
        # the vertical balance resting on the glass: 1/λ and g, both 1 in the paper mode (eq 9), Brenner's
        # and Goren & O'Neill's wall factors in the accurate mode
        lam0, g0 = normal_factors(self.mode, r, 0.0, self.roughness)
        self._inv_lambda_contact, self._flow_push_contact = 1.0 / float(lam0), float(g0)
        # the accurate mode's resistance functions as arrays, for lifted spheres in the kernel
        self._wall = tuple(wall_table()) if self.mode == "accurate" else _no_wall_table()
        poly = self._footprint
        self._edges = tuple(np.ascontiguousarray(a) for a in (poly.x0, poly.y0, poly.dx, poly.dy, poly.ab2, poly.y1))
        # robot–sphere lubrication per edge (accurate mode only: the paper's simulation had none)
        if lubrication not in ("edges", "face", "none"):
            raise ParameterError(f"lubrication must be 'edges', 'face' or 'none', got {lubrication!r}")
        self.lubrication = lubrication if self.mode == "accurate" else "none"
        if lubrication == "face":
            self.film_area = film_area(r, edge_curvatures(self.footprint))
            self.edge_law = np.zeros_like(self.film_area)
        else:
            self.film_area, self.edge_law = film_laws(self.geometry, r, self.params.edge_coefficient)
        self.contact_gap = float(contact_gap) if contact_gap is not None else self.params.contact_gap
        if self.contact_gap <= 0:
            raise ParameterError(f"contact_gap must be positive, got {self.contact_gap!r} m")
        on = self.lubrication != "none"
        self.film_cutoff = self.params.film_cutoff * r if on else 0.0
        self.edge_cutoff = self.params.edge_cutoff * r if on else 0.0

    @staticmethod
    def _count(init) -> int:
        if callable(init):
            probe = np.asarray(init(1, None))
            if probe.ndim != 3 or probe.shape[-1] != 2:
                raise WiringError(f"initial_positions callable must return (B, N, 2), got {probe.shape}")
            return probe.shape[1]
        arr = np.asarray(init, float)
        if arr.ndim not in (2, 3) or arr.shape[-1] != 2 or arr.shape[-2] < 1:
            raise WiringError(f"initial_positions must be (N, 2) or (B, N, 2) metres, got shape {arr.shape}")
        return arr.shape[-2]

    @property
    def flow(self) -> RobotFlow:
        """The robot's cached flow at the sphere-centre height (solved on first use)."""
        if self._flow is None:
            # sampled at the nominal centre height R + ε: a calibrated ε changes the lubrication
            # mobility (eq 4), not where the flow is read
            self._flow = robot_flow(self.geometry, self.viscosity, self.radius + self.params.roughness, self.domain)
        return self._flow

    def prepare(self) -> None:
        """Do the one-off work of the first frame now: solve the robot's flow (cached per process)
        and load or compile the frame kernel, so a real-time loop does not stall on its first frame."""
        state = self.initial_state(1)
        still = {"position": np.zeros((1, 2)), "heading": np.zeros(1), "velocity": np.zeros((1, 2))}
        self.update(state, still)

    @property
    def uses_random(self) -> bool:
        p = self.params
        return p.sticky_probability > 0 or p.release_scatter > 0

    # --- state ------------------------------------------------------------------------------
    def state_vars(self):
        n = self.n
        return (StateVar("xy", (n, 2), symbol="P_s", description="sphere centres, m"),
                StateVar("gap", (n,), symbol="δ", description="lift-off gap above the glass, m"),
                StateVar("mobility", (n,), symbol="m", description="per-sphere mobility factor (drawn at step 0)"),
                StateVar("contact", (), "bool", description="the robot touched a sphere in the previous frame"))

    def initial_state(self, batch: int, rng=None) -> dict:
        init = self.init(batch, rng) if callable(self.init) else self.init
        xy = np.broadcast_to(np.asarray(init, float), (batch, self.n, 2)).copy()
        if not np.all(np.isfinite(xy)):
            raise WiringError(f"block {self.name!r}: initial sphere positions must be finite")
        p = self.params
        # the mean mobility multiplier (models/sphere.toml variability.mobility_ratio, 1 = the model's own);
        # sticky patches and the mean-one lognormal scatter multiply it
        mult = np.full((batch, self.n), float(p.mobility))
        if rng is not None and self.uses_random:
            if p.sticky_probability > 0:
                sticky = rng.random((self.n,), at=0) < p.sticky_probability
                mult = np.where(sticky, p.sticky_mobility * mult, mult)
            if p.release_scatter > 0:
                sig = np.sqrt(np.log1p(p.release_scatter**2))
                mult = mult * np.exp(sig * rng.standard_normal((self.n,), at=0) - 0.5 * sig**2)
        xy = separate_spheres(xy, self.radius)
        return {"xy": xy, "gap": np.zeros((batch, self.n)), "mobility": mult,
                "contact": np.zeros(batch, bool)}

    # --- physics ----------------------------------------------------------------------------
    def sphere_velocity(self, xy, gap, mult, pos, heading, vel):
        """In-plane sphere velocity ``(B, N, 2)`` and gap rate ``(B, N)`` for the robot state given.

        The flow look-up, mobility (eq 4) and gap balance (eq 8-9) of a sub-step in numpy, at the sphere
        states given; a frame (sub-steps and contacts) is the kernel's."""
        c, s = _rot(np.asarray(heading, float))
        vel = np.asarray(vel, float)
        vbx, vby = c * vel[:, 0] + s * vel[:, 1], -s * vel[:, 0] + c * vel[:, 1]
        vx, vy, gap_rate, k = self._rates(xy[..., 0], xy[..., 1], gap, self._capped(mult, gap), pos,
                                          c[:, None], s[:, None], vbx[:, None], vby[:, None])
        return np.stack([k * vx, k * vy], axis=-1), gap_rate

    def _capped(self, mult, gap):
        """Mobility V_p/U per sphere (eq 4), capped at the free-sphere limit 1."""
        # a sphere cannot outrun the fluid around it: the free-sphere limit V_p/U = 1 caps the
        # mobility (eq 4's bounded coefficients exceed it away from contact, and so can scattered trials)
        k = np.full(gap.shape, self._k_contact)
        lifted = gap > 0
        if lifted.any():
            k[lifted] = mobility(self.mode, self.radius, gap[lifted], self.roughness)
        return np.minimum(k * mult, 1.0)

    def _gap_rate(self, uz, gap):
        """dδ/dt of eq 8-9: the flow's vertical velocity against buoyant weight and adhesion P.

        ``paper`` mode, eq 9 as printed: ``dδ/dt = U_z − (W_b + P)/(6πμR)``.

        ``accurate`` mode: the quasi-steady normal force balance on the sphere,
        ``−6πμR λ dδ/dt + 6πμR g U_z − W_b − P = 0``, so
        ``dδ/dt = (g U_z − (W_b + P)/(6πμR)) / λ`` at δ/R = (δ + ε)/R (roughness added as in eq 4):
        λ is Brenner's (1961) normal drag factor, g Goren & O'Neill's (1971) force of the wall flow
        on the held sphere. ``U_z`` is the flow's vertical velocity at the sphere centre, read from
        the flow map computed without the sphere. Near a no-slip wall any flow has ``u_z ∝ z²``
        (``u_z = ∂u_z/∂z = 0`` on the glass), and that local quadratic flow ``u_z = U_z (z/h)²`` —
        the vertical counterpart of the paper's local shear ``U z/h`` behind eq 4 — pushes a held
        sphere with 6πμR g U_z, g → 1 far from the wall and g → 3.23 at contact. Dividing by λ
        (≈ R/δ near contact) makes U_z's share of the gap rate vanish like δ: lifting a sphere off
        the glass needs fluid to enter the gap, and the lubrication pressure that resists settling
        resists it equally. Whether a sphere lifts (the sign of the rate) depends on ``g U_z``
        against the settling speed, not on λ.
        """
        if self.mode == "paper":
            if self.pull_off:
                pull = np.where(gap <= self.params.adhesion_range, self.pull_off, 0.0)
                return uz - (self.buoyant_weight + pull) / self.zeta
            return uz - self.buoyant_weight / self.zeta
        inv = np.full(np.shape(gap), self._inv_lambda_contact)
        push = np.full(np.shape(gap), self._flow_push_contact)
        lifted = gap > 0
        if lifted.any():
            lam, g = normal_factors(self.mode, self.radius, gap[lifted], self.roughness)
            inv[lifted], push[lifted] = 1.0 / lam, g
        if self.pull_off:
            pull = np.where(gap <= self.params.adhesion_range, self.pull_off, 0.0)
            rate = push * uz - (self.buoyant_weight + pull) / self.zeta
        else:
            rate = push * uz - self.buoyant_weight / self.zeta
        return rate * inv

    def _rates(self, x, y, gap, k, pos, c, s, vbx, vby):
        """World-frame flow velocity ``(v_x, v_y)`` at the spheres ``(x, y)`` (B, N), the gap rate
        (eq 8-9) and the mobility ``k`` passed through; ``c, s`` = cos/sin of the heading and
        ``vbx, vby`` the robot's body-frame velocity, each (B, 1)."""
        dx, dy = x - pos[:, 0, None], y - pos[:, 1, None]
        rx, ry = c * dx + s * dy, -s * dx + c * dy                      # robot frame
        ux, uy, uz = self.flow.lookup_components(rx, ry, vbx, vby)
        wx, wy = c * ux - s * uy, s * ux + c * uy                       # back to the world frame
        return wx, wy, self._gap_rate(uz, gap), k

    def _frame_args(self) -> tuple:
        """The arguments of :func:`~magctl.plant.sphere_kernel.trial_frame` after the robot's motion,
        up to the wall table: sub-steps, flow, footprint and the balance's constants."""
        flat, dgx, dgy = self.flow._flat_maps()
        return (self.params.substeps, self.dt / self.params.substeps, flat, self.flow.gx, self.flow.gy, dgx, dgy,
                self.flow.points, self.flow.forces, self.flow.eps, self.flow.viscosity, self.flow.height,
                *self._edges, self.film_area, self.edge_law, self.radius, self.reach, self._box[0], self._box[1],
                self.buoyant_weight / self.zeta,
                (self.buoyant_weight + self.pull_off) / self.zeta, self.params.adhesion_range, self._k_contact,
                self.mode == "paper", self.roughness, self._inv_lambda_contact, self._flow_push_contact,
                self.contact_gap, self.film_cutoff, self.edge_cutoff)

    def kernel(self):
        """The block's frame (:func:`~magctl.plant.sphere_kernel.spheres_update`), one trial per call, run by
        both engines. Solves the flow if not yet done."""
        from magctl.core.kernel import Kernel
        from magctl.plant import sphere_kernel as k

        pairs = max(self.n * (self.n - 1) // 2, 1)
        work = (np.zeros(pairs), np.zeros(pairs), np.zeros(8))     # scratch, rewritten by every call
        params = tuple(np.ascontiguousarray(a) if isinstance(a, np.ndarray) else a
                       for a in (*self._frame_args(), *self._wall, *work))
        return Kernel(output=k.spheres_output, update=k.spheres_update, params=params)


def _no_wall_table() -> tuple:
    """The kernel's table argument in the paper mode, which never reads it: read-only arrays
    of a :class:`~magctl.plant.fluid.wall_drag.WallTable`'s types, so both modes share one compilation."""
    arrays = (np.zeros(2), np.zeros((8, 1, 4)), np.ones(8))
    for a in arrays:
        a.flags.writeable = False
    return (*arrays, 0.0, 0.0, 0.0, 0.0)


def integrate_inertial(block: Spheres, start: np.ndarray, robot_path: Callable[[float], tuple], t_end: float,
                       rtol: float = 1e-6, atol: float = 1e-10):
    """One sphere under eq 6-7 with inertia, integrated with a stiff solver (scipy BDF).

    ``m dV/dt = F_G(U, V) = 6πμR c (k U - V)`` where ``c = -(F*_trans + (ΩR/V) F*_rot)`` is the
    resistance of eq 4-5 at contact and ``k`` the block's mobility V_p/U (so the inertia-free
    limit is exactly the block's Stokes mode); the gap is held at zero (W_b > 0 keeps the
    sphere on the glass). No contact handling.

    Parameters
    ----------
    robot_path : callable ``t -> (position (2,), heading, velocity (2,))``
    Returns
    -------
    t : ndarray, xy : ndarray (T, 2)
    """
    from magctl.plant.fluid.wall_drag import paper_coefficients, paper_rotation_ratio

    r = block.radius
    mass = block.params.density * 4.0 / 3.0 * np.pi * r**3
    _, f_trans, f_rot = paper_coefficients(r, 0.0, block.roughness)
    resist = -(f_trans + paper_rotation_ratio(r, r + block.roughness) * f_rot)   # > 0
    k = float(mobility(block.mode, r, 0.0, block.roughness))

    def rhs(t, y):
        pos, heading, vel = robot_path(t)
        rel = to_body(y[None, None, :2], np.asarray(pos, float)[None], np.asarray([heading], float))
        c, s = _rot(heading)
        vb = np.array([[c * vel[0] + s * vel[1], -s * vel[0] + c * vel[1]]])
        u = block.flow.lookup(rel, vb[:, None, :])
        u_xy = to_world(u[..., :2], np.asarray([heading], float))[0, 0]
        force = block.zeta * resist * (k * u_xy - y[2:])
        return np.concatenate([y[2:], force / mass])

    sol = solve_ivp(rhs, (0.0, t_end), np.concatenate([np.asarray(start, float), [0.0, 0.0]]), method="BDF",
                    rtol=rtol, atol=atol, dense_output=True)
    if not sol.success:
        raise RuntimeError(f"inertial sphere integration failed: {sol.message}")
    return sol.t, sol.y[:2].T
