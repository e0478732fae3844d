"""The kinematic stand-in plant: one robot, one sphere model, one tracker, composed three ways.

The stand-in replaces the paper's physics (stick-slip gait, Stokes flow, camera, Kalman
tracker) with kinematics and the paper's empirical laws, so that loops run in microseconds
per frame and their outcome can be checked against closed forms. It keeps the port names,
shapes and units of docs/interfaces.md. Its blocks:

* :class:`KinematicRobot` — ``speed``, ``heading`` in; ``position``, ``heading``, ``velocity``
  out. ``x[k+1] = x[k] + T·speed·(cos h, sin h)``: the robot moves at the commanded speed
  within one frame and turns at once (the integrator ``P(z) = T/(z − 1)`` of the servo
  analysis, §II). The **one** kinematic robot of the package.
* :class:`FieldGait` — the delivered coil field → the steady speed and heading the robot
  settles to (heading along ``b_static``, speed ``v = f·s(θ_a)`` of
  :func:`magctl.plant.robot.steady_speed`); with a :class:`KinematicRobot` it is the
  field-driven stand-in robot.
* :class:`StraightToTarget` — the ideal servo the iteration-domain attempt maps of
  :mod:`magctl.stability.iteration` assume: speed and heading that take the robot straight to
  ``target`` at ``min(speed_cap, v_max)``, landing on it exactly.
* :class:`StandinSpheres` — spheres pushed by contact, displaced by a side pass (eq 22),
  pulled back on release by ``D_p,r ~ N(μ, σ²)`` (§IV-D), kept apart from each other.
* :class:`StandinTracker` — exact positions one frame late; ``lost`` outside the field of
  view or in a blackout window; spheres reported missing (NaN) in a sphere-loss window.

Compositions (the blocks are the same objects in each):

1. the rig's fast plant, :func:`magctl.loops.plant` with ``kind="standin"``:
   ``CoilActuator → FieldGait → KinematicRobot → StandinSpheres → StandinTracker``;
2. the servo analysis' plant, :func:`magctl.stability.servo.servo_step_diagram`:
   ``Servo → KinematicRobot → Camera → Tracker``;
3. the push tasks under the attempt maps' assumptions (tests):
   ``task → StraightToTarget → KinematicRobot → StandinSpheres → StandinTracker``.

Parameters come from ``models/rig.toml`` ``[standin]`` (geometry, field of view) and
``models/push.toml`` ``[release]`` (``D_p,r``); see :func:`standin_params`.

Each block's behaviour is its kernel in :mod:`magctl.plant.standin_kernels`, run by both engines; the numpy
forms they are tested against are in ``tests/reference/plant_blocks.py``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magctl import FRAME_PERIOD_S
from magctl.config import load_model
from magctl.core.block import Block, StateVar, rng_var
from magctl.core.errors import MagctlError
from magctl.core.kernel import Kernel
from magctl.core.ports import Port
from magctl.plant.fluid.calibration import paper_side
from magctl.plant.fluid.params import sphere_params
from magctl.plant.robot import ROBOT_INPUTS

__all__ = ["FieldGait", "KinematicRobot", "StandinParams", "StandinSpheres", "StandinTracker", "StraightToTarget",
           "standin_params"]

_STRAIGHT = np.cos(np.deg2rad(1.0))
"""Two frames' directions within 1° of each other continue a straight path (eq 22 applies only to those)."""


@dataclass(frozen=True)
class StandinParams:
    """Parameters of the stand-in plant (SI).

    Attributes
    ----------
    contact_distance : float
        Robot centre to sphere centre at contact, m (robot contact radius + sphere radius).
    sphere_radius : float
        Sphere radius ``a``, m; two spheres closer than ``2a`` are separated.
    side_range : float
        Lateral distance beyond which a side pass leaves a sphere alone (eq 22 cut-off), m.
    workspace_half : float
        Half side of the tracker's square field of view round the origin, m.
    release_mean, release_std : float
        ``μ`` and ``σ`` of ``D_p,r`` (§IV-D), m.
    """

    contact_distance: float
    sphere_radius: float
    side_range: float
    workspace_half: float
    release_mean: float
    release_std: float


def standin_params() -> StandinParams:
    """The stand-in's parameters: ``models/rig.toml`` ``[standin]``, ``models/push.toml`` ``[release]`` and
    ``[front] contact_um`` (the push tasks' own release and contact distance) and the sphere radius of
    ``models/sphere.toml``."""
    sd = load_model("rig").standin
    push = load_model("push")
    release = push.release
    radius = sphere_params().radius
    return StandinParams(contact_distance=float(push.front.contact),
                         sphere_radius=float(radius), side_range=float(sd.side_range),
                         workspace_half=float(sd.workspace_half), release_mean=float(release.mean),
                         release_std=float(release.std))


# --- the robot ------------------------------------------------------------------------------------------
class KinematicRobot(Block):
    """Kinematic robot: ``x[k+1] = x[k] + T·speed[k]·(cos h[k], sin h[k])``, heading set at once.

    The robot moves at the commanded speed within one frame and turns instantly: the
    plant ``P(z) = T/(z − 1)`` the linear servo analysis assumes (§II, docs/sensing-servo.md).
    Its position after ``K`` frames is ``start + T·Σₖ speed[k]·(cos h[k], sin h[k])``.

    Parameters
    ----------
    name : str
    start : (2,) array_like
        Initial position, m.
    heading0 : float
        Initial heading, rad.
    steer_input : bool
        Add an input ``steer`` () bool: the heading follows the ``heading`` input while it is
        true (a robot aligning to a static field at rest). Without it the heading follows the
        input while ``speed > 0`` and is held otherwise.
    dt : float
        Frame period ``T``, s.

    Ports
    -----
    inputs ``speed`` () m/s, ``heading`` () rad [, ``steer`` () bool];
    outputs ``position`` (2,) m, ``heading`` () rad, ``velocity`` (2,) m/s (over the last frame).
    """

    def __init__(self, name: str = "robot", *, start=(0.0, 0.0), heading0: float = 0.0, steer_input: bool = False,
                 dt: float = FRAME_PERIOD_S):
        self.start = np.asarray(start, dtype=float).reshape(2)
        self.heading0 = float(heading0)
        inputs = [Port("speed", (), "m/s"), Port("heading", (), "rad")]
        if steer_input:
            inputs.append(Port("steer", (), "1", "bool"))
        super().__init__(name, inputs=inputs,
                         outputs=[Port("position", (2,), "m"), Port("heading", (), "rad"),
                                  Port("velocity", (2,), "m/s")], dt=dt, feedthrough=False)

    def state_vars(self):
        return (StateVar("x", (2,), symbol="x", description="position, m"),
                StateVar("h", (), symbol="ψ", description="heading, rad"),
                StateVar("v", (2,), symbol="v", description="velocity over the previous frame, m/s"))

    def initial_state(self, batch, rng=None):
        return {"x": np.broadcast_to(self.start, (batch, 2)).copy(), "h": np.full(batch, self.heading0),
                "v": np.zeros((batch, 2))}

    def kernel(self):
        from magctl.plant import standin_kernels as k

        update = k.kinematic_robot_steer_update if "steer" in self.inputs else k.kinematic_robot_update
        return Kernel(output=k.kinematic_robot_output, update=update, params=(float(self.dt),))

    def jacobians(self, state, u):
        """Exact ``(A, B, C, D)`` of trial 0 for :func:`magctl.core.linearize.linearize_diagram`.

        State ``(x₀, x₁, h, v₀, v₁)``, inputs ``(speed, heading)``, outputs ``(position, heading,
        velocity)`` — the declared real state and ports in order. With ``s`` the speed and ``ψ`` the
        commanded heading: ``∂x⁺/∂s = T (cos ψ, sin ψ)``, ``∂x⁺/∂ψ = T s (−sin ψ, cos ψ)``, ``∂v⁺``
        the same without ``T``; the heading state follows ``ψ`` while steering and holds otherwise.
        """
        s, psi = float(u["speed"][0]), float(u["heading"][0])
        steer = bool(u["steer"][0]) if "steer" in u else s > 0
        c, si = np.cos(psi), np.sin(psi)
        A = np.zeros((5, 5))
        A[0, 0] = A[1, 1] = 1.0
        A[2, 2] = 0.0 if steer else 1.0
        B = np.zeros((5, 2))
        B[0:2, 0] = self.dt * np.array([c, si])
        B[0:2, 1] = self.dt * s * np.array([-si, c])
        B[2, 1] = 1.0 if steer else 0.0
        B[3:5, 0] = [c, si]
        B[3:5, 1] = s * np.array([-si, c])
        return A, B, np.eye(5), np.zeros((5, 2))


class FieldGait(Block):
    """Delivered field → the steady speed and heading of the stick-slip robot (no dynamics).

    Heading along the static field ``b_static``; speed ``v = f·s(θ_a)``, the speed the
    stick-slip robot block settles to for a held field (:func:`magctl.plant.robot.steady_speed`),
    so the drive's inverse of that law commands the intended speed. No field, no motion and no
    steering (``steer`` false). Wired into a :class:`KinematicRobot` with ``steer_input=True``
    it is the field-driven stand-in robot.

    Parameters
    ----------
    name : str
    robot : StickSlipParams
        Robot parameters (``magctl.plant.robot.load_robot()``).

    Ports
    -----
    inputs ``b_static_delivered`` (2,) T, ``b_osc_delivered`` () T, ``freq_delivered`` () 1/s;
    outputs ``speed`` () m/s, ``heading`` () rad, ``steer`` () bool. Feedthrough.
    """

    def __init__(self, name: str, robot, dt: float = FRAME_PERIOD_S):
        self.robot = robot
        super().__init__(name, inputs=list(ROBOT_INPUTS),
                         outputs=[Port("speed", (), "m/s"), Port("heading", (), "rad"),
                                  Port("steer", (), "1", "bool")], dt=dt, feedthrough=True)

    def kernel(self):
        from magctl.plant import standin_kernels as k

        p = self.robot
        # the products _stickslip forms from the parameters alone, formed the same way
        return Kernel(step=k.field_gait_step, params=(p.pitch_drag_ratio * p.turn_drag, p.moment,
                                                      p.slip_efficiency * p.length, float(np.cos(p.break_angle))))


class StraightToTarget(Block):
    """The ideal servo of the attempt maps: straight to ``target`` at ``min(speed_cap, v_max)``.

    ``speed = min(cap, ‖target − x‖/T)`` with ``cap = min(speed_cap, v_max)`` (0 when
    ``speed_cap ≤ 0``) and ``heading`` towards the target, so a :class:`KinematicRobot` fed
    with them lands on the target exactly — the servo the iteration-domain maps of
    :mod:`magctl.stability.iteration` assume (no overshoot, no shortfall, §V). It reads the
    robot's true ``position``, not the tracker's estimate.

    Parameters
    ----------
    name : str
    v_max : float
        Speed limit, m/s.

    Ports
    -----
    inputs ``target`` (2,) m, ``speed_cap`` () m/s, ``position`` (2,) m;
    outputs ``speed`` () m/s, ``heading`` () rad. Feedthrough.
    """

    def __init__(self, name: str = "servo", *, v_max: float = 1e-3, dt: float = FRAME_PERIOD_S):
        self.v_max = float(v_max)
        super().__init__(name, inputs=[Port("target", (2,), "m"), Port("speed_cap", (), "m/s"),
                                       Port("position", (2,), "m")],
                         outputs=[Port("speed", (), "m/s"), Port("heading", (), "rad")], dt=dt, feedthrough=True)

    def kernel(self):
        from magctl.plant import standin_kernels as k

        return Kernel(step=k.straight_to_target_step, params=(self.v_max, float(self.dt)))


# --- the spheres ------------------------------------------------------------------------------------------
class StandinSpheres(Block):
    """Spheres moved by contact and by two empirical fluid effects of the paper.

    Per frame, with the robot moving from ``r₀`` (last frame) to ``r`` along the unit
    vector ``d``, every sphere in turn:

    1. **side pass** (eq 22): a sphere the robot passes on a straight path (direction within
       1° of the last frame's) at lateral centre distance ``D_g``, contact < ``D_g`` <
       ``side_range`` — its along-track coordinate changes sign — moves
       ``D_s = 1755 µm · exp(−0.009042 D_g/µm)`` along ``d``, once per straight pass;
    2. **release** (§IV-D, Fig 1d): when the robot moves away from a sphere it was pushing,
       the sphere follows it for ``D_p,r ~ N(μ, σ²)`` (the experiments' 300 ± 75 µm; clipped
       at 0), at most the robot's step per frame. One standard normal draw per trial and
       frame; a release started this frame uses it. The outputs ``releases`` (count so far)
       and ``last_release`` (the latest ``D_p,r``) expose the drawn amounts;
    3. **contact**: a sphere ahead of the moving robot (``(s − r)·d ≥ 0``) and inside its
       contact disc (lateral offset ``ℓ`` < ``contact_distance`` = ``c``) is carried along ``d``
       to ``(s − r)·d = √(c² − ℓ²)``, keeping its lateral offset: it sits in the robot's front
       notch, so a push moves it along the robot's path as the attempt maps assume (§V-A). Any
       other sphere closer than ``c`` (the robot at rest, or the sphere beside or behind it) is
       pushed out along the line of centres. A sphere so moved is attached and will be released;
    4. **sphere–sphere**: two spheres closer than ``2a`` are separated to ``2a`` along their
       line of centres by moving the one the robot did not drive this frame (by contact or
       release); if both were driven, the lower-indexed one gives way.

    Motion lags the robot's by one frame (the block reads the robot's position output).

    Parameters
    ----------
    name : str
    start : (N, 2) array_like
        Initial sphere centres, m.
    contact_distance : float
        Robot contact radius plus sphere radius, m.
    release_mean, release_std : float
        ``μ``, ``σ`` of ``D_p,r``, m (0, 0: no release).
    side_range : float
        Lateral distance beyond which a pass leaves the sphere alone, m (0: no side pass).
    sphere_radius : float
        ``a``, m (0: spheres pass through each other).
    start_robot : (2,) array_like
        Robot position before the first frame, m.
    side_scale : float or (B,) array_like
        Multiplies eq 22's displacement (one value per trial allowed): a plant whose side-push curve is
        eq 22 scaled, for the mismatched-plant checks of the side-push analysis (default 1).

    Ports
    -----
    inputs ``position`` (2,) m (the robot's); outputs ``spheres`` (N, 2) m, ``contact`` () bool,
    ``releases`` () 1 (count), ``last_release`` () m.
    """

    def __init__(self, name: str, start, contact_distance: float, *, release_mean: float = 0.0,
                 release_std: float = 0.0, side_range: float = 0.0, sphere_radius: float = 0.0, start_robot=(0.0, 0.0),
                 side_scale=1.0, dt: float = FRAME_PERIOD_S):
        self.start = np.asarray(start, dtype=float).reshape(-1, 2)
        eq22 = paper_side()                                  # D_s = A exp(−k D_g)
        self.side_amplitude, self.side_rate = eq22["amplitude"], eq22["rate"]
        self.contact_distance = float(contact_distance)
        self.release_mean, self.release_std = float(release_mean), float(release_std)
        self.side_range = float(side_range)
        self.side_scale = np.asarray(side_scale, dtype=float)
        if self.side_scale.ndim > 1 or not np.all(np.isfinite(self.side_scale)) or np.any(self.side_scale <= 0):
            raise MagctlError(f"stand-in spheres {name!r}: side_scale {side_scale!r} must be positive, "
                              "a number or one per trial")
        self.sphere_radius = float(sphere_radius)
        self.start_robot = np.asarray(start_robot, dtype=float).reshape(2)
        n = self.start.shape[0]
        super().__init__(
            name,
            inputs=[Port("position", (2,), "m")],
            outputs=[Port("spheres", (n, 2), "m"), Port("contact", (), "1", "bool"), Port("releases", (), "1"),
                     Port("last_release", (), "m")],
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
                StateVar("releases", (), symbol="n_r", description="releases so far"),
                StateVar("last_release", (), symbol="D_p,r", description="amount of the last release, m"),
                rng_var("release displacement draws, read at position k"),
                StateVar("k", (), "int64", "k", "frames stepped (the stream position)", batched=False))

    def initial_state(self, batch, rng=None):
        n = self.start.shape[0]
        return {"s": np.broadcast_to(self.start, (batch, n, 2)).copy(), "contact": np.zeros(batch, dtype=bool),
                "r": np.broadcast_to(self.start_robot, (batch, 2)).copy(), "dir": np.zeros((batch, 2)),
                "attached": np.zeros((batch, n), dtype=bool), "pending": np.zeros((batch, n)),
                "passed": np.zeros((batch, n), dtype=bool), "releases": np.zeros(batch),
                "last_release": np.zeros(batch), "rng": rng, "k": 0}

    def kernel(self):
        from magctl.plant import standin_kernels as k

        n = self.start.shape[0]
        params = (n, self.contact_distance, self.release_mean, self.release_std, self.side_range,
                  self.side_amplitude, self.side_rate, np.array(self.side_scale, float).reshape(-1),
                  2.0 * self.sphere_radius, float(_STRAIGHT), np.zeros(max(n, 1), bool))
        return Kernel(output=k.standin_spheres_output, update=k.standin_spheres_update, params=params,
                      stream="rng")


# --- the tracker ------------------------------------------------------------------------------------------
class StandinTracker(Block):
    """Exact positions one frame late; tracking and sphere loss by field of view and by window.

    The estimate shown at time ``t = kT`` is the true state of frame ``k − 1``. ``lost`` is
    true when the robot is outside the square field of view ``|x|, |y| ≤ half_width`` or ``t``
    lies in the ``blackout`` window; in the ``sphere_loss`` window every sphere estimate is
    NaN (the tracker reports the spheres missing; the position estimates carry on).

    Parameters
    ----------
    name : str
    n_spheres : int
        Number of spheres.
    half_width : float
        Half side of the field of view centred at the origin, m.
    blackout, sphere_loss : (float, float) or None
        Windows ``[t0, t1)`` in s of forced tracking loss / sphere loss (``t1`` may be ``inf``).
    start, heading0, spheres0
        The estimate before the first frame (robot position m, heading rad, sphere centres m).

    Ports
    -----
    inputs ``position`` (2,) m, ``heading`` () rad, ``spheres`` (N, 2) m;
    outputs ``robot_est`` (2,) m, ``heading_est`` () rad, ``velocity_est`` (2,) m/s,
    ``spheres_est`` (N, 2) m, ``lost`` () bool.
    """

    def __init__(self, name: str, n_spheres: int, half_width: float, blackout=None, start=(0.0, 0.0),
                 heading0: float = 0.0, spheres0=None, *, sphere_loss=None, dt: float = FRAME_PERIOD_S):
        self.half_width = float(half_width)
        self.blackout = None if blackout is None else (float(blackout[0]), float(blackout[1]))
        self.sphere_loss = None if sphere_loss is None else (float(sphere_loss[0]), float(sphere_loss[1]))
        self.start = np.asarray(start, dtype=float).reshape(2)
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
                StateVar("k", (), "int64", "k", "frames stepped (for the windows)", batched=False))

    def initial_state(self, batch, rng=None):
        return {"r": np.broadcast_to(self.start, (batch, 2)).copy(), "h": np.full(batch, self.heading0),
                "v": np.zeros((batch, 2)),
                "s": np.broadcast_to(self.spheres0, (batch, *self.spheres0.shape)).copy(),
                "lost": np.zeros(batch, dtype=bool), "k": 0}

    def kernel(self):
        from magctl.plant import standin_kernels as k

        black = self.blackout or (0.0, 0.0)
        loss = self.sphere_loss or (0.0, 0.0)
        return Kernel(output=k.standin_tracker_output, update=k.standin_tracker_update,
                      params=(float(self.dt), self.half_width, self.blackout is not None, *black,
                              self.sphere_loss is not None, *loss))

