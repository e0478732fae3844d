"""A kinematic STAND-IN plant for the simulated rig.

These blocks exist so that the rig (adapter, server, runtime, logs) can be
built and tested before the physical plant blocks of ``magctl.plant`` are
wired in. They honour the port names, shapes and units of docs/interfaces.md
but not the physics of the paper:

* coils: the actuator's field-to-current allocation with its current limits (no RL dynamics);
* robot: the heading follows the static field instantly and the robot moves
  along it at the steady stick-slip speed of ``magctl.plant.robot.steady_speed``
  for the delivered field (no heading lag, no speed noise, no tilt output);
* spheres: pushed by contact (moved out of the robot's contact disc), plus two
  empirical fluid effects instead of the Stokes-flow model — the side-pass
  displacement of eq 22 and the release displacement D_p,r ~ N(300, 75²) µm
  measured in §IV-D; no sphere–sphere contact;
* tracker: exact positions one frame late; ``lost`` outside the field of view
  or during a configured blackout.

They are the fast option (``--plant standin``) of :func:`magctl.rig.plant.build_sim_plant`,
whose default is the physical plant; nothing else in :mod:`magctl.rig` depends on this module.
"""

from __future__ import annotations

import numpy as np

from magctl import FRAME_PERIOD_S
from magctl.core.block import Block, StateVar, rng_var
from magctl.core.ports import Port
from magctl.plant.robot import ROBOT_INPUTS, ROBOT_OUTPUTS
from magctl.rig.interface import CoilMap

FIELD_IN = [Port("b_static", (2,), "T"), Port("b_osc", (), "T"), Port("freq", (), "1/s")]


class StandinCoils(Block):
    """Field command → coil currents with the amplifier limits, no RL dynamics (stand-in for ``magctl.plant.coils``).

    Currents come from the actuator's allocation (:class:`~magctl.rig.interface.CoilMap`). A static
    field that would exceed a coil's rating is scaled down (direction kept), the oscillation takes
    at most the current left, and the command is flagged ``saturated``.
    """

    def __init__(self, name: str, coils: CoilMap, dt: float = FRAME_PERIOD_S):
        self.coils = coils
        super().__init__(
            name,
            inputs=FIELD_IN,
            outputs=[Port("currents", (6,), "A"), Port("b_static_delivered", (2,), "T"),
                     Port("b_osc_delivered", (), "T"), Port("freq_delivered", (), "1/s"),
                     Port("saturated", (), "1", "bool")],
            dt=dt, feedthrough=True,
        )
        per_t = coils.osc_currents(np.ones(1))[0]
        self._osc_coils = per_t > 1e-9 * per_t.max()
        self._osc_per_t = per_t[self._osc_coils]

    def output(self, state, u):
        bs, bo = u["b_static"], np.abs(u["b_osc"])
        lim = self.coils.current_limit
        i_s = self.coils.static_currents(bs)
        s = np.minimum(1.0, np.min(lim / np.maximum(np.abs(i_s), 1e-300), axis=1))
        bs_d, i_s = bs * s[:, None], i_s * s[:, None]
        bo_lim = np.min((lim - np.abs(i_s))[:, self._osc_coils] / self._osc_per_t, axis=1)
        bo_d = np.minimum(bo, np.maximum(bo_lim, 0.0))
        return {
            "currents": i_s,
            "b_static_delivered": bs_d,
            "b_osc_delivered": bo_d,
            "freq_delivered": u["freq"].copy(),
            "saturated": (s < 1.0) | (bo > bo_lim),
        }


class StandinRobot(Block):
    """Kinematic robot: heading along ``b_static`` at once, steady stick-slip speed along it.

    The speed is ``v = f·s(θ_a)`` of :func:`magctl.plant.robot.steady_speed` (the speed the
    real robot block settles to for a held field), so the drive's inverse of that law commands
    the intended speed.

    Parameters
    ----------
    robot : StickSlipParams
        Robot parameters (``magctl.plant.robot.load_robot()``).
    start : (2,) array
        Initial position, m.
    heading0 : float
        Initial heading, rad.
    """

    def __init__(self, name: str, robot, start=(0.0, 0.0), heading0: float = 0.0, dt: float = FRAME_PERIOD_S):
        self.robot = robot
        self.start, self.heading0 = np.asarray(start, dtype=float), float(heading0)
        super().__init__(
            name,
            inputs=list(ROBOT_INPUTS),
            outputs=list(ROBOT_OUTPUTS),
            dt=dt, feedthrough=False,
        )

    def state_vars(self):
        return (StateVar("p", (2,), symbol="p", description="position, m"),
                StateVar("h", (), symbol="ψ", description="heading, rad"),
                StateVar("v", (2,), symbol="v", description="velocity over the previous frame, m/s"))

    def initial_state(self, batch, rng=None):
        return {"p": np.broadcast_to(self.start, (batch, 2)).copy(), "h": np.full(batch, self.heading0),
                "v": np.zeros((batch, 2))}

    def output(self, state, u):
        return {"position": state["p"], "heading": state["h"], "velocity": state["v"],
                "tilt": np.zeros_like(state["h"])}

    def update(self, state, u):
        from magctl.plant.robot import steady_speed

        bs = u["b_static_delivered"]
        b_xy = np.sqrt(np.einsum("bi,bi->b", bs, bs))
        h = np.where(b_xy > 0, np.arctan2(bs[:, 1], bs[:, 0]), state["h"])
        speed = np.where(b_xy > 0, steady_speed(self.robot, b_xy, u["b_osc_delivered"], u["freq_delivered"]), 0.0)
        v = speed[:, None] * np.stack([np.cos(h), np.sin(h)], axis=1)
        # new arrays: outputs handed out this step stay untouched
        return {"p": state["p"] + v * self.dt, "h": h, "v": v}


class StandinSpheres(Block):
    """Spheres moved by contact and by two empirical fluid effects of the paper.

    Per frame, with the robot moving from ``r₀`` (last frame) to ``r`` along ``d``:

    1. **side pass** (eq 22): a sphere the robot passes on a straight path at lateral
       centre distance ``D_g`` (contact < D_g < ``side_range``) — its along-track
       coordinate changes sign — moves ``D_s = 1755 µm · exp(−0.009042 D_g/µm)`` along ``d``;
    2. **release** (§IV-D, Fig 1d): when the robot moves away from a sphere it was pushing,
       the sphere follows it for ``D_p,r ~ N(μ, σ²)`` (the experiments' 300 ± 75 µm),
       at most the robot's step per frame;
    3. **contact**: a sphere closer than ``contact_distance`` to ``r`` is pushed out along the
       line of centres.

    No sphere–sphere contact. Its motion lags the robot's by one frame.

    Parameters
    ----------
    start : (N, 2) array
        Initial sphere centres, m.
    contact_distance : float
        Robot contact radius plus sphere radius, m.
    release_mean, release_std : float
        Mean and standard deviation of ``D_p,r``, m.
    side_range : float
        Lateral distance beyond which a pass leaves the sphere alone, m.
    """

    # eq 22: D_s = A exp(−k D_g)
    SIDE_A = 1755e-6
    SIDE_K = 0.009042e6

    def __init__(self, name: str, start, contact_distance: float, *, release_mean: float = 0.0,
                 release_std: float = 0.0, side_range: float = 0.0, start_robot=(0.0, 0.0), dt: float = FRAME_PERIOD_S):
        self.start = np.asarray(start, dtype=float).reshape(-1, 2)
        self.contact_distance = float(contact_distance)
        self.release_mean, self.release_std = float(release_mean), float(release_std)
        self.side_range = float(side_range)
        self.start_robot = np.asarray(start_robot, dtype=float)
        n = self.start.shape[0]
        super().__init__(
            name,
            inputs=[Port("position", (2,), "m"), Port("heading", (), "rad"), Port("velocity", (2,), "m/s")],
            outputs=[Port("spheres", (n, 2), "m"), Port("contact", (), "1", "bool")],
            dt=dt, feedthrough=False,
        )

    @property
    def uses_random(self) -> bool:
        return True

    def state_vars(self):
        n = self.start.shape[0]
        return (StateVar("s", (n, 2), symbol="P_s", description="sphere centres, m"),
                StateVar("contact", (), "bool", description="a sphere was pushed in the previous frame"),
                StateVar("r", (2,), symbol="r₀", description="robot position of the previous frame, m"),
                StateVar("dir", (2,), symbol="d", description="unit direction of the robot's last move"),
                StateVar("attached", (n,), "bool", description="sphere touching the robot"),
                StateVar("pending", (n,), symbol="D_p,r", description="release displacement still to follow, m"),
                StateVar("passed", (n,), "bool", description="already displaced by the current straight pass"),
                rng_var("release displacement draws, read at position k"),
                StateVar("k", (), "int64", "k", "frames stepped (the stream position)", batched=False))

    def initial_state(self, batch, rng=None):
        n = self.start.shape[0]
        return {"s": np.broadcast_to(self.start, (batch, n, 2)).copy(), "contact": np.zeros(batch, dtype=bool),
                "r": np.broadcast_to(self.start_robot, (batch, 2)).copy(), "dir": np.zeros((batch, 2)),
                "attached": np.zeros((batch, n), dtype=bool), "pending": np.zeros((batch, n)),
                "passed": np.zeros((batch, n), dtype=bool), "rng": rng, "k": 0}

    def output(self, state, u):
        return {"spheres": state["s"], "contact": state["contact"]}

    def update(self, state, u):
        s = state["s"]
        r0, r = state["r"], u["position"]
        draw = state["rng"].standard_normal((), at=state["k"]) if state["rng"] is not None else np.zeros(r.shape[0])
        if s.shape[1] == 0:
            return {**state, "r": r.copy(), "k": state["k"] + 1}
        step = r - r0
        size = np.sqrt(np.einsum("bi,bi->b", step, step))
        moving = size > 1e-12
        d = np.where(moving[:, None], step / np.where(moving, size, 1.0)[:, None], 0.0)
        straight = moving & (np.einsum("bi,bi->b", d, state["dir"]) > np.cos(np.deg2rad(1.0)))
        passed = state["passed"] & straight[:, None]  # one displacement per straight pass
        dd = d[:, None, :]

        # 1. side pass, eq 22
        rel0 = s - r0[:, None, :]
        a0 = np.einsum("bni,bni->bn", rel0, np.broadcast_to(dd, rel0.shape))
        a1 = np.einsum("bni,bni->bn", s - r[:, None, :], np.broadcast_to(dd, rel0.shape))
        lat = np.abs(dd[..., 0] * rel0[..., 1] - dd[..., 1] * rel0[..., 0])
        cross = (straight[:, None] & ~passed & (a0 > 0) & (a1 <= 0) & (lat > self.contact_distance)
                 & (lat < self.side_range))
        s = s + (cross * self.SIDE_A * np.exp(-self.SIDE_K * lat))[..., None] * dd
        passed = passed | cross

        # 2. release: the sphere follows a robot that moves away from it
        away = moving[:, None] & (np.einsum("bni,bni->bn", s - r[:, None, :], np.broadcast_to(dd, s.shape)) < 0)
        release = state["attached"] & away
        amount = np.maximum(0.0, self.release_mean + self.release_std * draw)[:, None]
        pending = np.where(release, amount, state["pending"])
        follow = np.where(away, np.minimum(pending, size[:, None]), 0.0)
        s = s + follow[..., None] * dd
        pending = pending - follow
        attached = state["attached"] & ~release

        # 3. contact
        rel = s - r[:, None, :]
        dist = np.sqrt(np.einsum("bni,bni->bn", rel, rel))
        over = dist < self.contact_distance * (1 - 1e-9)  # a rounding-level overlap (a following sphere) is none
        pushed = r[:, None, :] + rel * (self.contact_distance / np.where(dist > 0, dist, 1.0))[..., None]
        s = np.where(over[..., None], pushed, s)
        # a sphere left exactly at contact distance still touches (unless the robot is leaving it): whether
        # rounding puts it a hair inside or outside must not decide whether it is released later
        touching = over | ((dist < self.contact_distance * (1 + 1e-9)) & ~away)
        return {"s": s, "contact": over.any(axis=1), "r": r.copy(), "dir": np.where(moving[:, None], d, state["dir"]),
                "attached": attached | touching, "pending": np.where(touching, 0.0, pending), "passed": passed,
                "rng": state["rng"], "k": state["k"] + 1}


class StandinTracker(Block):
    """Exact positions one frame late; ``lost`` outside the field of view or during a blackout.

    Parameters
    ----------
    n_spheres : int
        Number of spheres.
    half_width : float
        Half side of the square field of view centred at the origin, m.
    blackout : (float, float) or None
        Time window ``[t0, t1)`` in s during which tracking is reported lost.
    """

    def __init__(self, name: str, n_spheres: int, half_width: float, blackout=None, start=(0.0, 0.0),
                 heading0: float = 0.0, spheres0=None, dt: float = FRAME_PERIOD_S):
        self.half_width = float(half_width)
        self.blackout = None if blackout is None else (float(blackout[0]), float(blackout[1]))
        self.start = np.asarray(start, dtype=float)
        self.heading0 = float(heading0)
        self.spheres0 = np.zeros((n_spheres, 2)) if spheres0 is None else np.asarray(spheres0, float).reshape(-1, 2)
        super().__init__(
            name,
            inputs=[Port("position", (2,), "m"), Port("heading", (), "rad"), Port("spheres", (n_spheres, 2), "m")],
            outputs=[Port("robot_est", (2,), "m"), Port("heading_est", (), "rad"), Port("velocity_est", (2,), "m/s"),
                     Port("spheres_est", (n_spheres, 2), "m"), Port("lost", (), "1", "bool")],
            dt=dt, feedthrough=False,
        )

    def state_vars(self):
        n = self.spheres0.shape[0]
        return (StateVar("r", (2,), symbol="p", description="robot position seen last frame, m"),
                StateVar("h", (), symbol="ψ", description="robot heading seen last frame, rad"),
                StateVar("v", (2,), symbol="v", description="finite-difference velocity, m/s"),
                StateVar("s", (n, 2), symbol="P_s", description="sphere centres seen last frame, m"),
                StateVar("lost", (), "bool", description="tracking lost"),
                StateVar("k", (), "int64", "k", "frames stepped (for the blackout window)", batched=False))

    def initial_state(self, batch, rng=None):
        return {"r": np.broadcast_to(self.start, (batch, 2)).copy(), "h": np.full(batch, self.heading0),
                "v": np.zeros((batch, 2)),
                "s": np.broadcast_to(self.spheres0, (batch, *self.spheres0.shape)).copy(),
                "lost": np.zeros(batch, dtype=bool), "k": 0}

    def output(self, state, u):
        return {"robot_est": state["r"], "heading_est": state["h"], "velocity_est": state["v"],
                "spheres_est": state["s"], "lost": state["lost"]}

    def update(self, state, u):
        p = u["position"]
        k = state["k"] + 1
        lost = np.any(np.abs(p) > self.half_width, axis=1)
        if self.blackout is not None and self.blackout[0] <= k * self.dt < self.blackout[1]:
            lost = np.ones_like(lost)
        return {"r": p.copy(), "h": u["heading"].copy(), "v": (p - state["r"]) / self.dt,
                "s": u["spheres"].copy(), "lost": lost, "k": k}
