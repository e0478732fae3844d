"""The plant factory behind the simulated rig.

:func:`build_sim_plant` returns a :class:`~magctl.core.Diagram` with the
contract the rig server and :class:`~magctl.rig.sim.SimRig` rely on:

* exported inputs ``b_static`` (2,) T, ``b_osc`` () T, ``freq`` () 1/s — the drive's field command;
* exported outputs ``robot_est`` (2,) m, ``heading_est`` () rad, ``spheres_est`` (N, 2) m,
  ``lost`` () bool — the tracker's observation — and ``currents`` (6,) A.

Two plants honour it:

``physics`` (default)
    The blocks of the closed-loop simulation (:func:`magctl.loops.push_loop` without its
    task, servo and drive): :class:`~magctl.plant.coils.CoilActuator` →
    :class:`~magctl.plant.robot.StickSlipRobot` → :class:`~magctl.plant.sphere.Spheres` (Stokes
    flow and contact) → :class:`~magctl.sensing.camera.Camera` (positions mode, primed with the
    scene) → :class:`~magctl.sensing.tracker.Tracker` (Kalman). A :class:`Blackout` gate between
    camera and tracker drops frames in a configured window, so the tracker really loses track.
``standin``
    The fast kinematic stand-in of :mod:`magctl.plant.standin`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from magctl import FRAME_PERIOD_S
from magctl.config import Params, load_model
from magctl.core.block import Block
from magctl.core.diagram import Diagram
from magctl.core.errors import WiringError
from magctl.core.linear import Constant
from magctl.core.ports import DIMENSIONLESS, Port
from magctl.plant.robot import load_robot
from magctl.plant.standin import StandinCoils, StandinRobot, StandinSpheres, StandinTracker
from magctl.rig.interface import CoilMap

PLANT_INPUTS = ("b_static", "b_osc", "freq")
PLANT_OUTPUTS = ("robot_est", "heading_est", "spheres_est", "lost", "currents")
PLANTS = ("physics", "standin")


@dataclass
class Scene:
    """Initial layout of a simulated rig (SI).

    Attributes
    ----------
    robot : (2,) array
        Robot start position, m.
    heading : float
        Robot start heading, rad.
    spheres : (N, 2) array
        Sphere centres, m.
    blackout : (float, float) or None
        Window ``[t0, t1)`` in s of forced tracking loss (for tests of loss handling).
    """

    robot: np.ndarray = field(default_factory=lambda: np.zeros(2))
    heading: float = 0.0
    spheres: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    blackout: tuple[float, float] | None = None

    @classmethod
    def default(cls, n_spheres: int, params: Params | None = None, **kw) -> Scene:
        """Robot at ``scene.robot_start`` heading +x, spheres ahead of it on its line every ``scene.sphere_spacing``.

        This is the starting layout of the paper's experiments (§VI): the robot 1 mm from the sphere,
        placed inside the camera's field of view.
        """
        if n_spheres < 0:
            raise WiringError(f"n_spheres must be >= 0, got {n_spheres}")
        p = params or load_model("rig")
        start = np.asarray(p.scene.robot_start, dtype=float)
        gap = p.scene.sphere_spacing
        spheres = np.array([start + (gap * (i + 1), 0.0) for i in range(n_spheres)]).reshape(-1, 2)
        return cls(robot=start, spheres=spheres, **kw)

    def to_dict(self) -> dict:
        return {"robot_um": (self.robot * 1e6).tolist(), "heading_rad": self.heading,
                "spheres_um": (self.spheres * 1e6).tolist(),
                "blackout_s": None if self.blackout is None else list(self.blackout)}


class Blackout(Block):
    """Camera frames dropped during a time window ``[t0, t1)``: ``valid_out = valid ∧ ¬blackout``.

    Sits between the camera and the tracker so that a blackout is a real loss of detections
    (the tracker coasts, then reports ``lost``), for tests of the controller's loss handling.

    Parameters
    ----------
    window : (float, float) or None
        ``[t0, t1)`` in s of plant time; None passes every frame.
    """

    def __init__(self, name: str = "blackout", window=None, dt: float = FRAME_PERIOD_S):
        self.window = None if window is None else (float(window[0]), float(window[1]))
        super().__init__(name, inputs=[Port("valid", (), DIMENSIONLESS, "bool")],
                         outputs=[Port("valid_out", (), DIMENSIONLESS, "bool")], dt=dt, feedthrough=True)

    def initial_state(self, batch, rng=None):
        return {"k": 0}

    def output(self, state, u):
        w = self.window
        if w is not None and w[0] <= state["k"] * self.dt < w[1]:
            return {"valid_out": np.zeros_like(u["valid"])}
        return {"valid_out": u["valid"]}

    def update(self, state, u):
        return {"k": state["k"] + 1}


def build_sim_plant(n_spheres: int, scene: Scene | None = None, params: Params | None = None,
                    robot_start: Sequence[float] | None = None, plant: str = "physics") -> Diagram:
    """The simulated rig's plant: field command in, tracker observation out.

    Parameters
    ----------
    n_spheres : int
        Number of spheres in the scene (the length of ``spheres_est``).
    scene : Scene, optional
        Initial layout; :meth:`Scene.default` when omitted.
    params : Params, optional
        ``models/rig.toml`` (loaded when omitted).
    robot_start : (2,) sequence, optional
        Overrides ``scene.robot``.
    plant : {"physics", "standin"}
        The physical plant blocks (default) or the fast kinematic stand-in.

    Returns
    -------
    Diagram
        Inputs ``b_static``, ``b_osc``, ``freq``; outputs ``robot_est``, ``heading_est``,
        ``spheres_est``, ``lost``, ``currents``.
    """
    if plant not in PLANTS:
        raise WiringError(f"plant {plant!r} is not one of {', '.join(PLANTS)}")
    p = params or load_model("rig")
    scene = scene or Scene.default(n_spheres, p)
    if scene.spheres.shape != (n_spheres, 2):
        raise WiringError(f"scene has {scene.spheres.shape[0]} spheres but n_spheres={n_spheres}")
    if robot_start is not None:
        scene = dataclasses.replace(scene, robot=np.asarray(robot_start, dtype=float))
    build = _physics_plant if plant == "physics" else _standin_plant
    return build(n_spheres, scene, p)


def _physics_plant(n: int, scene: Scene, p: Params) -> Diagram:
    from magctl.loops import calibrated_roughness
    from magctl.plant.coils import CoilActuator
    from magctl.plant.fluid.params import sphere_params
    from magctl.plant.robot import StickSlipRobot
    from magctl.plant.sphere import Spheres
    from magctl.sensing.camera import Camera
    from magctl.sensing.tracker import Tracker

    ph = p.physics
    start, heading, spheres0 = np.asarray(scene.robot, float), float(scene.heading), scene.spheres
    camera_kw = {} if ph.camera_noise else {"position_noise_px": 0.0, "heading_noise": 0.0}
    camera = Camera(n_spheres=n, primed=(start, heading, spheres0), **camera_kw)
    _check_in_view(camera, start, spheres0)
    blocks = [
        CoilActuator("coils"),
        StickSlipRobot("robot", position=start, heading=heading, variability=bool(ph.robot_steps)),
        camera,
        Blackout("blackout", scene.blackout),
        Tracker(n_spheres=n, init_robot=start, init_heading=heading, init_spheres=spheres0),
    ]
    wires = [
        ("coils.b_static_delivered", "robot.b_static_delivered"), ("coils.b_osc_delivered", "robot.b_osc_delivered"),
        ("coils.freq_delivered", "robot.freq_delivered"),
        ("robot.position", "camera.position"), ("robot.heading", "camera.heading"),
        ("camera.robot_meas", "tracker.robot_meas"), ("camera.heading_meas", "tracker.heading_meas"),
        ("camera.spheres_meas", "tracker.spheres_meas"), ("camera.valid", "blackout.valid"),
        ("blackout.valid_out", "tracker.valid"),
    ]
    if n:
        sp = dataclasses.replace(sphere_params(), release_scatter=float(ph.release_scatter))
        spheres = Spheres(spheres0, params=sp, roughness=calibrated_roughness() if ph.calibrated_release else None)
        spheres.prepare()  # flow solve and kernel compile (~1 s, once per process) now, not in the first served frame
        blocks.append(spheres)
        wires += [("robot.position", "spheres.position"), ("robot.heading", "spheres.heading"),
                  ("robot.velocity", "spheres.velocity"), ("spheres.spheres", "camera.spheres")]
    else:  # the sphere block needs at least one sphere; an empty scene feeds the camera none
        blocks.append(Constant("spheres", np.zeros((0, 2)), shape=(0, 2), unit="m"))
        wires.append(("spheres.y", "camera.spheres"))
    return Diagram(
        "sim_plant", blocks, connections=wires,
        inputs={"b_static": "coils.b_static", "b_osc": "coils.b_osc", "freq": "coils.freq"},
        outputs={"robot_est": "tracker.robot_est", "heading_est": "tracker.heading_est",
                 "spheres_est": "tracker.spheres_est", "lost": "tracker.lost", "currents": "coils.currents"},
    )


def _check_in_view(camera, robot: np.ndarray, spheres: np.ndarray) -> None:
    """The scene must start inside the camera's field of view, or the tracker starts lost."""
    w, h = camera.field_of_view
    pts = np.vstack([robot[None], spheres])
    out = (pts[:, 0] < 0) | (pts[:, 0] > w) | (pts[:, 1] < 0) | (pts[:, 1] > h)
    if out.any():
        raise WiringError(
            f"scene point(s) {np.round(pts[out] * 1e6, 1).tolist()} µm lie outside the camera's field of view "
            f"[0, {w * 1e6:.0f}] × [0, {h * 1e6:.0f}] µm; place the robot and the spheres inside it")


def _standin_plant(n: int, scene: Scene, p: Params) -> Diagram:
    start = np.asarray(scene.robot, float)
    sd = p.standin
    coils = StandinCoils("coils", CoilMap.from_coils())
    robot = StandinRobot("robot", load_robot(), start, scene.heading)
    spheres = StandinSpheres("spheres", scene.spheres, sd.robot_contact_radius + sd.sphere_radius,
                             release_mean=sd.release_mean, release_std=sd.release_std, side_range=sd.side_range,
                             start_robot=start)
    tracker = StandinTracker("tracker", n, sd.workspace_half, scene.blackout, start, scene.heading, scene.spheres)
    return Diagram(
        "sim_plant",
        [coils, robot, spheres, tracker],
        connections=[
            ("coils.b_static_delivered", "robot.b_static_delivered"),
            ("coils.b_osc_delivered", "robot.b_osc_delivered"),
            ("coils.freq_delivered", "robot.freq_delivered"),
            ("robot.position", "spheres.position"),
            ("robot.heading", "spheres.heading"),
            ("robot.velocity", "spheres.velocity"),
            ("robot.position", "tracker.position"),
            ("robot.heading", "tracker.heading"),
            ("spheres.spheres", "tracker.spheres"),
        ],
        inputs={"b_static": "coils.b_static", "b_osc": "coils.b_osc", "freq": "coils.freq"},
        outputs={"robot_est": "tracker.robot_est", "heading_est": "tracker.heading_est",
                 "spheres_est": "tracker.spheres_est", "lost": "tracker.lost", "currents": "coils.currents"},
    )


def check_plant(diagram: Diagram) -> None:
    """Raise :class:`WiringError` unless ``diagram`` exports the rig plant's ports."""
    missing_in = [n for n in PLANT_INPUTS if n not in diagram.inputs]
    missing_out = [n for n in PLANT_OUTPUTS if n not in diagram.outputs]
    if missing_in or missing_out:
        raise WiringError(
            f"plant diagram {diagram.name!r} lacks inputs {missing_in} / outputs {missing_out} "
            f"(needs inputs {list(PLANT_INPUTS)} and outputs {list(PLANT_OUTPUTS)})"
        )
