"""The paper's push experiments (§VI) as batched 30 Hz closed loops.

One diagram per experiment::

    push task → PI servo → drive → coils → stick-slip robot → spheres (Stokes flow, contact)
        ↑                                                            │
        └──────────── tracker (Kalman) ←── camera (lag, pixels) ◄────┘

built from the same blocks the rig runs (:func:`magctl.studies.trials.run_push_trials`
steps batches of it).

The variability that makes trials differ (:class:`Variability`) is seeded per
trial: camera noise and quantisation (tracking noise), stick-slip step
variability of the robot, lognormal scatter of the sphere's flow mobility (the
spread of the release displacement D_p,r, §IV-D) and sticky patches on the glass
(§VI-B).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from magctl.config import load_model
from magctl.control.push.assembly import AssemblyTask
from magctl.control.push.front import FrontAssemblyTask, FrontPushTask
from magctl.control.push.side import SidePushTask
from magctl.control.servo import Servo, servo_params
from magctl.core import Diagram
from magctl.core.errors import MagctlError
from magctl.plant.drive import ActuatedRobot
from magctl.plant.fluid.params import sphere_params
from magctl.plant.sphere import Spheres
from magctl.sensing.camera import Camera
from magctl.sensing.tracker import Tracker

UM = 1e-6
ORIGIN = np.array([2.0e-3, 1.8e-3])
"""Where the (first) sphere starts: near the middle of the 4.8 × 3.6 mm camera field."""


@dataclass(frozen=True)
class Variability:
    """Sources of trial-to-trial variation (each seeded per trial).

    Attributes
    ----------
    camera_noise : bool
        Pixel noise and dropped frames of the camera (otherwise only quantisation).
    robot_steps : bool
        Per-step stick-slip variability of the robot.
    release_scatter : float
        Relative (lognormal) spread of the sphere's mobility in the robot's flow; sets
        the scatter of the release displacement D_p,r. With the calibrated plant 0.1
        gives D_p,r = 306 ± 64 µm (200 seeded trials), the measured 300 ± 75 µm (§IV-D).
    sticky_probability : float
        Probability that a sphere sits on a sticky patch (§VI-B, "stuck on dirt").
    calibrated : bool
        Use the sphere–glass gap ε fitted to the measured D_p,r = 300 µm
        (``models/sphere.toml`` [calibration]) instead of the measured 25 nm roughness.
    """

    camera_noise: bool = True
    robot_steps: bool = True
    release_scatter: float = 0.1
    sticky_probability: float = 0.0
    calibrated: bool = False

    def describe(self) -> str:
        on = [name for name, v in (("camera noise", self.camera_noise), ("robot step variability", self.robot_steps),
                                   (f"release scatter ±{self.release_scatter:.0%}", self.release_scatter > 0),
                                   (f"sticky patches p={self.sticky_probability:g}", self.sticky_probability > 0),
                                   ("D_p,r-calibrated sphere-glass gap", self.calibrated))
              if v]
        return ", ".join(on) if on else "none (deterministic)"


@dataclass(frozen=True)
class Experiment:
    """One controller in one of the paper's set-ups (§VI), picklable for process pools.

    Attributes
    ----------
    kind : {"front", "side", "assembly", "front-assembly"}
        Task: front push (§V-A), side push (§V-B), side-push assembly (§V-C) or the
        front-push assembly the paper shows failing (Fig 3).
    task : dict
        Keyword arguments of the task class (gains, model, fixed gap, …).
    max_frames : int
        Frames after which a still-running trial is cut off.
    servo : {"default", "tuned"}
        Servo parameter set (``models/servo.toml``).
    variability : Variability
    label : str
        Controller label for figures and tables.
    """

    kind: str
    task: dict = field(default_factory=dict)
    max_frames: int = 3000
    servo: str = "default"
    variability: Variability = Variability()
    label: str = ""


def calibrated_roughness() -> float:
    """The D_p,r-calibrated sphere–glass gap ε [m] from ``models/sphere.toml``."""
    return float(load_model("sphere").calibration.release_roughness)


def geometry(kind: str) -> dict:
    """Start positions and goal of the paper's set-ups (§VI), in metres.

    Front push: goal 750 µm beyond the sphere, robot 1 mm behind it on the pushing line.
    Side push: goal 300 µm from the sphere, robot 1 mm away. Assembly: a second sphere
    600 µm (centre to centre) from the first.
    """
    sphere = ORIGIN.copy()
    if kind == "front":
        return {"spheres": sphere[None], "robot": sphere - (1e-3, 0.0), "goal": sphere + (750 * UM, 0.0)}
    if kind == "side":
        return {"spheres": sphere[None], "robot": sphere - (1e-3, 0.0), "goal": sphere + (0.0, 300 * UM)}
    if kind in ("assembly", "front-assembly"):
        second = sphere + (600 * UM, 0.0)
        return {"spheres": np.stack([sphere, second]), "robot": sphere - (1e-3, 0.0), "goal": second}
    raise MagctlError(f"experiment kind {kind!r} is not one of front, side, assembly, front-assembly")


def build_task(exp: Experiment):
    g = geometry(exp.kind)
    kw = dict(exp.task)
    if exp.kind == "front":
        return FrontPushTask("task", goal=g["goal"], **kw)
    if exp.kind == "side":
        return SidePushTask("task", goal=g["goal"], **kw)
    if exp.kind == "assembly":
        return AssemblyTask("task", n_spheres=2, **kw)
    return FrontAssemblyTask("task", n_spheres=2, **kw)


def push_loop(exp: Experiment) -> Diagram:
    """The closed-loop diagram of one experiment."""
    g = geometry(exp.kind)
    n = len(g["spheres"])
    var = exp.variability
    sp = dataclasses.replace(sphere_params(), release_scatter=var.release_scatter,
                             sticky_probability=var.sticky_probability)
    camera_kw = {} if var.camera_noise else {"position_noise_px": 0.0, "heading_noise": 0.0, "drop_probability": 0.0}
    blocks = [
        ActuatedRobot("plant", position=g["robot"], variability=var.robot_steps),
        Spheres(g["spheres"], params=sp, roughness=calibrated_roughness() if var.calibrated else None),
        Camera(n_spheres=n, primed=(g["robot"], 0.0, g["spheres"]), **camera_kw),
        Tracker(n_spheres=n, init_robot=g["robot"], init_spheres=g["spheres"]),
        Servo(params=servo_params(exp.servo), speed_cap_input=True, hold_input=True),
        build_task(exp),
    ]
    wires = [
        ("plant.position", "spheres.position"), ("plant.heading", "spheres.heading"),
        ("plant.velocity", "spheres.velocity"), ("plant.position", "camera.position"),
        ("plant.heading", "camera.heading"), ("spheres.spheres", "camera.spheres"),
        ("camera.robot_meas", "tracker.robot_meas"), ("camera.heading_meas", "tracker.heading_meas"),
        ("camera.spheres_meas", "tracker.spheres_meas"), ("camera.valid", "tracker.valid"),
        ("tracker.robot_est", "task.robot_est"), ("tracker.spheres_est", "task.spheres_est"),
        ("tracker.lost", "task.lost"), ("task.target", "servo.target"), ("tracker.robot_est", "servo.robot_est"),
        ("task.speed_cap", "servo.speed_cap"), ("tracker.lost", "servo.hold"),
        ("servo.speed", "plant.speed"), ("servo.heading", "plant.heading"),
    ]
    return Diagram(f"{exp.kind}_push_loop", blocks, wires)
