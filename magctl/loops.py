"""The closed loop, wired in one place: :func:`controller` and :func:`plant` built once, and the two connected.

::

     controller(task)                                   plant(scene, variability)
    ┌────────────────────────────────────┐  field cmd  ┌───────────────────────────────────────────────┐
    │ task ─► PI servo ─► drive          │────────────►│ coils ─► robot ─► spheres ─► camera ─► tracker │
    │  ▲ (push law,  (hold on   (speed,  │ b_static,   │ (RL,     (stick-  (Stokes    (lag,   (Kalman)  │
    │  │  planner)    loss)   heading→B) │ b_osc, freq │ limits)   slip)    flow)     pixels)           │
    └──┼─────────────────────────────────┘             └───────────────────────────────────────┬───────┘
       └──────────── robot_est, spheres_est, lost ◄─────────────────────────────────────────────┘

The studies connect the two halves with :func:`closed_loop`; the rig runtime steps the very
:func:`controller` diagram against a hardware adapter, and ``magctl rig serve-sim`` serves the
very :func:`plant` diagram. Nothing else in magctl wires a task, a servo, a drive or a plant
chain together.

The controller's exported inputs are ``robot_est`` (2,) m, ``spheres_est`` (N, 2) m and
``lost`` () bool (a subset of the rig's observation); its exported outputs are the field
command ``b_static`` (2,) T, ``b_osc`` () T, ``freq`` () 1/s, the task's ``status``
(:class:`~magctl.control.status.Status`) and the task's own outputs. The plant's exported
inputs are the field command; its outputs are the tracker's ``robot_est``, ``heading_est``,
``spheres_est``, ``lost`` and the coils' ``currents`` (6,) A.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from magctl.config import Params, load_model
from magctl.control.guards import ArrivalStatus, Patrol
from magctl.control.push.assembly import AssemblyTask, FrontThenSideAssemblyTask
from magctl.control.push.front import FrontAssemblyTask, FrontPushTask
from magctl.control.push.planned import PlannedAssemblyTask
from magctl.control.push.side import SidePushTask
from magctl.control.push_params import goal_distance
from magctl.control.servo import Servo, servo_params
from magctl.core.batched import perp, unit
from magctl.core.diagram import Diagram
from magctl.core.errors import MagctlError, WiringError
from magctl.core.linear import Constant
from magctl.core.units import UM
from magctl.plant.coils import CoilActuator
from magctl.plant.drive import Drive
from magctl.plant.fluid.params import sphere_params
from magctl.plant.robot import StickSlipRobot, load_robot
from magctl.plant.sphere import Spheres
from magctl.plant.standin import FieldGait, KinematicRobot, StandinSpheres, StandinTracker, standin_params
from magctl.sensing.blackout import Blackout
from magctl.sensing.camera import Camera, outside_view
from magctl.sensing.tracker import Tracker

COMMAND = ("b_static", "b_osc", "freq")
"""The field command: the controller's outputs, the plant's inputs."""
OBSERVATION = ("robot_est", "heading_est", "spheres_est", "lost")
"""The tracker's estimate: the plant's outputs, a superset of the controller's inputs."""
PLANT_OUTPUTS = (*OBSERVATION, "currents")
PUSH_TASKS = {"front-push": FrontPushTask, "side-push": SidePushTask, "assemble": AssemblyTask,
              "front-assemble": FrontAssemblyTask, "front-side-assemble": FrontThenSideAssemblyTask}
TASKS = ("goto", "patrol", *PUSH_TASKS)
ASSEMBLY_TASKS = ("assemble", "front-assemble", "front-side-assemble")
PLANTS = ("physics", "standin")

__all__ = ["ASSEMBLY_TASKS", "COMMAND",
           "OBSERVATION", "PLANTS", "PLANT_OUTPUTS", "PUSH_TASKS", "TASKS", "Experiment", "Scene",
           "Variability", "closed_loop", "controller", "default_goal", "experiment_controller", "geometry", "plant",
           "push_loop", "sphere_count"]


# --- the controller ---------------------------------------------------------------------------------------
def controller(task: str, *, n_spheres: int, goal=None, target=None, waypoints=None, servo: str | None = None,
               speed_max: float | None = None, **task_options: Any) -> Diagram:
    """Task → PI servo → drive, as one diagram (the controller half of the loop).

    Parameters
    ----------
    task : {"goto", "patrol", "front-push", "side-push", "assemble", "front-assemble", "front-side-assemble"}
        ``goto``: servo to ``target`` and stop (status ``CONVERGED`` on arrival). ``patrol``: drive
        round ``waypoints`` forever. The push tasks are §V-A (eq 10–13), §V-B (eq 16–18), §V-C
        (eq 21, by side pushing), the front-push assembly the paper shows failing (Fig 3) and the
        paper's Fig 15 protocol (one front push, then side-push assembly).
    n_spheres : int
        Width of the ``spheres_est`` input (push tasks).
    goal : (2,) or (B, 2) array_like, optional
        ``P_g`` in m of ``front-push`` and ``side-push`` (see :func:`default_goal`).
    target : (2,) array_like
        Go-to target, m.
    waypoints : (K, 2) array_like
        Patrol waypoints, m.
    servo : str, optional
        Servo setting of ``models/servo.toml`` (its ``[choice] default`` when omitted).
    speed_max : float, optional
        Servo speed limit, m/s (the setting's when omitted).
    **task_options
        Keyword arguments of the push task's block (gains, model, fixed gap, tolerances …; SI);
        the ones not given come from ``models/push.toml``.

    Returns
    -------
    Diagram
        Named ``controller``: inputs ``robot_est`` [, ``spheres_est``], ``lost``; outputs
        ``b_static``, ``b_osc``, ``freq``, ``status`` and the task's other outputs.
    """
    if task not in TASKS:
        raise MagctlError(f"unknown task {task!r}; tasks: {', '.join(TASKS)}")
    is_push = task in PUSH_TASKS
    sp = servo_params(servo)
    servo_block = Servo("servo", params=sp, speed_max=speed_max, speed_cap_input=is_push, hold_input=True)
    blocks: list = [servo_block, Drive("drive")]
    wires = [("servo.speed", "drive.speed"), ("servo.heading", "drive.heading")]
    inputs: dict[str, list[str]] = {"robot_est": ["servo.robot_est"], "lost": ["servo.hold"]}
    outputs = {name: f"drive.{name}" for name in COMMAND}
    if is_push:
        block = _push_task_block(task, n_spheres, goal, task_options)
        blocks.insert(0, block)
        wires += [("task.target", "servo.target"), ("task.speed_cap", "servo.speed_cap")]
        inputs["robot_est"].append("task.robot_est")
        inputs["lost"].append("task.lost")
        inputs["spheres_est"] = ["task.spheres_est"]
        outputs |= {p: f"task.{p}" for p in block.outputs if p != "speed_cap"}
    elif task_options:
        raise MagctlError(f"task {task!r} takes no options {sorted(task_options)}")
    elif task == "goto":
        if target is None:
            raise MagctlError("task 'goto' needs a target")
        blocks += [Constant("goal", np.asarray(target, dtype=float), shape=(2,), unit="m"), ArrivalStatus("task")]
        wires += [("goal.y", "servo.target"), ("servo.arrived", "task.arrived")]
        inputs["lost"].append("task.lost")
        outputs |= {"status": "task.status", "target": "goal.y"}
    else:
        if waypoints is None:
            raise MagctlError("task 'patrol' needs waypoints")
        blocks.insert(0, Patrol("task", waypoints, 2.0 * servo_block.arrive_tol))
        wires.append(("task.target", "servo.target"))
        inputs["robot_est"].append("task.robot_est")
        outputs |= {"status": "task.status", "lap": "task.lap", "target": "task.target"}
    return Diagram("controller", blocks, wires, inputs=inputs, outputs=outputs)


def _push_task_block(task: str, n_spheres: int, goal, options: dict):
    cls = PUSH_TASKS[task]
    kw = dict(options)
    if task == "assemble" and (n_spheres > 2 or kw.keys() & {"arrangement", "planner"}):
        cls = PlannedAssemblyTask  # N spheres, or a pair by planned passes (docs/push-control.md §8)
    if task in ("front-push", "side-push"):
        if goal is None:
            raise MagctlError(f"task {task!r} needs a goal")
        kw["goal"] = goal
    elif goal is not None:
        raise MagctlError(f"task {task!r} takes no goal: it assembles the spheres where they lie")
    try:
        return cls("task", n_spheres=n_spheres, **kw)
    except TypeError as err:  # an option the block does not have
        raise MagctlError(f"task {task!r}: {err}") from None


def default_goal(task: str, robot, spheres) -> np.ndarray:
    """The goal of a push task when none is given: the paper's set-ups (§VI), from where things are.

    Front push: ``goal_distance`` (750 µm) beyond sphere 0, on the line from the robot through it.
    Side push: ``goal_distance`` (300 µm) from sphere 0, square to that line (to its left).
    Distances from ``models/push.toml``.
    """
    robot, s0 = np.asarray(robot, dtype=float), np.asarray(spheres, dtype=float)[0]
    away = unit(s0 - robot)
    if task == "front-push":
        return s0 + goal_distance("front") * away
    if task == "side-push":
        return s0 + goal_distance("side") * perp(away)
    raise MagctlError(f"task {task!r} has no goal (only front-push and side-push do)")


def sphere_count(task: str) -> int:
    """Spheres a task needs tracked: 2 for the assemblies, 1 for the pushes, 0 otherwise."""
    return 2 if task in ASSEMBLY_TASKS else 1 if task in PUSH_TASKS else 0


# --- the plant ---------------------------------------------------------------------------------------------
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
        gives D_p,r = 289 ± 90 µm in the task (200 seeded trials; measured 300 ± 75 µm, §IV-D).
    sticky_probability : float
        Probability that a sphere sits on a sticky patch (§VI-B, "stuck on dirt").
    contact_gap : float, optional
        The robot–sphere gap at rough contact ``h_min`` [m] instead of ``models/sphere.toml [contact]``
        (the in-task calibration, :mod:`magctl.studies.release_calibration`, scans it).
    """

    camera_noise: bool = True
    robot_steps: bool = True
    release_scatter: float = 0.1
    sticky_probability: float = 0.0
    contact_gap: float | None = None

    @classmethod
    def of_rig(cls, params: Params | None = None) -> Variability:
        """The simulated rig's variability (``models/rig.toml`` ``[physics]``)."""
        ph = (params or load_model("rig")).physics
        return cls(camera_noise=bool(ph.camera_noise), robot_steps=bool(ph.robot_steps),
                   release_scatter=float(ph.release_scatter))

    def describe(self) -> str:
        on = [name for name, v in (("camera noise", self.camera_noise), ("robot step variability", self.robot_steps),
                                   (f"release scatter ±{self.release_scatter:.0%}", self.release_scatter > 0),
                                   (f"sticky patches p={self.sticky_probability:g}", self.sticky_probability > 0),
                                   (f"robot-sphere contact gap {(self.contact_gap or 0) * 1e6:.3g} µm",
                                    self.contact_gap is not None))
              if v]
        return ", ".join(on) if on else "none (deterministic)"



@dataclass
class Scene:
    """Initial layout of a plant (SI).

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

    def __post_init__(self):
        self.robot = np.asarray(self.robot, dtype=float).reshape(2)
        self.spheres = np.asarray(self.spheres, dtype=float).reshape(-1, 2)
        self.heading = float(self.heading)

    @classmethod
    def default(cls, n_spheres: int, params: Params | None = None, **kw) -> Scene:
        """The paper's starting layout (§VI): robot at ``scene.robot_start`` heading +x, spheres ahead of
        it on its line every ``scene.sphere_spacing`` (1 mm), inside the camera field (``models/rig.toml``)."""
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


def plant(scene: Scene, variability: Variability | None = None, *, kind: str = "physics",
          truth: bool = False) -> Diagram:
    """Coils → robot → spheres → camera → tracker, as one diagram (the plant half of the loop).

    Parameters
    ----------
    scene : Scene
        Where the robot and the spheres start (must lie inside the camera field).
    variability : Variability, optional
        Sources of trial-to-trial variation (default: :class:`Variability()`).
    kind : {"physics", "standin"}
        The physical plant (coil RL dynamics and limits, stick-slip robot, Stokes flow and
        contact, camera lag and pixels, Kalman tracker) or the fast kinematic stand-in of
        :mod:`magctl.plant.standin` (empirical eq 22 and D_p,r instead of the flow).
    truth : bool
        Also export the true state the camera looks at — ``robot_true`` (2,) m, ``heading_true`` () rad and
        ``spheres_true`` (N, 2) m — for the simulated camera of the hardware path
        (:mod:`magctl.rig.devices.simulated`), which renders frames of it.

    Returns
    -------
    Diagram
        Named ``plant``: inputs ``b_static``, ``b_osc``, ``freq``; outputs ``robot_est``,
        ``heading_est``, ``spheres_est``, ``lost``, ``currents``.
    """
    if kind not in PLANTS:
        raise WiringError(f"plant {kind!r} is not one of {', '.join(PLANTS)}")
    var = Variability() if variability is None else variability
    diagram = (_physics_plant if kind == "physics" else _standin_plant)(scene, var)
    if not truth:
        return diagram
    spheres = "spheres.spheres" if len(scene.spheres) or kind != "physics" else "spheres.y"
    return Diagram("plant", list(diagram.blocks.values()), diagram.connections, inputs=diagram.exported_inputs,
                   outputs={**diagram.exported_outputs, "robot_true": "robot.position", "heading_true": "robot.heading",
                            "spheres_true": spheres})


def _physics_plant(scene: Scene, var: Variability) -> Diagram:
    n = len(scene.spheres)
    camera_kw = {} if var.camera_noise else {"position_noise_px": 0.0, "heading_noise": 0.0, "drop_probability": 0.0}
    camera = Camera(n_spheres=n, primed=(scene.robot, scene.heading, scene.spheres), **camera_kw)
    _check_in_view(camera, scene.robot, scene.spheres)
    blocks = [
        CoilActuator("coils"),
        StickSlipRobot("robot", position=scene.robot, heading=scene.heading, variability=var.robot_steps),
        camera,
        Blackout("blackout", scene.blackout),
        Tracker(n_spheres=n, init_robot=scene.robot, init_heading=scene.heading, init_spheres=scene.spheres),
    ]
    wires = [
        *_delivered_field_to("robot"),
        ("robot.position", "camera.position"), ("robot.heading", "camera.heading"),
        ("camera.robot_meas", "tracker.robot_meas"), ("camera.heading_meas", "tracker.heading_meas"),
        ("camera.spheres_meas", "tracker.spheres_meas"), ("camera.valid", "blackout.valid"),
        ("blackout.valid_out", "tracker.valid"),
    ]
    if n:
        sp = dataclasses.replace(sphere_params(), release_scatter=var.release_scatter,
                                 sticky_probability=var.sticky_probability)
        blocks.append(Spheres(scene.spheres, params=sp, contact_gap=var.contact_gap))
        wires += [("robot.position", "spheres.position"), ("robot.heading", "spheres.heading"),
                  ("robot.velocity", "spheres.velocity"), ("spheres.spheres", "camera.spheres")]
    else:  # the sphere block needs at least one sphere; an empty scene feeds the camera none
        blocks.append(Constant("spheres", np.zeros((0, 2)), shape=(0, 2), unit="m"))
        wires.append(("spheres.y", "camera.spheres"))
    return _plant_diagram(blocks, wires)


def _standin_plant(scene: Scene, var: Variability) -> Diagram:
    """Coils → gait → kinematic robot → stand-in spheres → stand-in tracker (:mod:`magctl.plant.standin`)."""
    sp = standin_params()
    blocks = [
        CoilActuator("coils"),
        FieldGait("gait", load_robot()),
        KinematicRobot("robot", start=scene.robot, heading0=scene.heading, steer_input=True),
        StandinSpheres("spheres", scene.spheres, sp.contact_distance, release_mean=sp.release_mean,
                       release_std=sp.release_std if var.release_scatter > 0 else 0.0, side_range=sp.side_range,
                       sphere_radius=sp.sphere_radius, start_robot=scene.robot),
        StandinTracker("tracker", len(scene.spheres), sp.workspace_half, scene.blackout, scene.robot, scene.heading,
                       scene.spheres),
    ]
    wires = [
        *_delivered_field_to("gait"),
        ("gait.speed", "robot.speed"), ("gait.heading", "robot.heading"), ("gait.steer", "robot.steer"),
        ("robot.position", "spheres.position"), ("robot.position", "tracker.position"),
        ("robot.heading", "tracker.heading"), ("spheres.spheres", "tracker.spheres"),
    ]
    return _plant_diagram(blocks, wires)


def _delivered_field_to(block: str) -> list[tuple[str, str]]:
    """The coils' delivered field into ``block``'s inputs of the same names."""
    return [(f"coils.{p}", f"{block}.{p}") for p in ("b_static_delivered", "b_osc_delivered", "freq_delivered")]


def _plant_diagram(blocks, wires) -> Diagram:
    return Diagram("plant", blocks, wires, inputs={name: f"coils.{name}" for name in COMMAND},
                   outputs={"robot_est": "tracker.robot_est", "heading_est": "tracker.heading_est",
                            "spheres_est": "tracker.spheres_est", "lost": "tracker.lost",
                            "currents": "coils.currents"})


def _check_in_view(camera: Camera, robot: np.ndarray, spheres: np.ndarray) -> None:
    """The scene must start inside the camera's field of view, or the tracker starts lost."""
    w, h = camera.field_of_view
    pts = np.vstack([robot[None], spheres])
    out = outside_view(pts, (w, h))
    if out.any():
        raise WiringError(
            f"scene point(s) {np.round(pts[out] / UM, 1).tolist()} µm lie outside the camera's field of view "
            f"[0, {w / UM:.0f}] × [0, {h / UM:.0f}] µm; place the robot and the spheres inside it")


# --- the closed loop ----------------------------------------------------------------------------------------
def closed_loop(ctrl: Diagram, plnt: Diagram, name: str = "loop") -> Diagram:
    """``ctrl`` and ``plnt`` connected: field command forward, tracker estimate back.

    Leaf signals are recorded as ``"controller/task.status"``, ``"plant/robot.position"`` ….
    """
    feedback = [(f"plant.{p}", f"controller.{p}") for p in OBSERVATION if p in ctrl.inputs]
    missing = sorted(set(ctrl.inputs) - set(OBSERVATION))
    if missing:
        raise WiringError(f"controller inputs {missing} are not plant outputs {list(OBSERVATION)}")
    forward = [(f"controller.{p}", f"plant.{p}") for p in COMMAND]
    return Diagram(name, [ctrl, plnt], [*forward, *feedback])


# --- the paper's experiments (§VI) as closed loops -----------------------------------------------------------
EXPERIMENT_TASKS = {"front": "front-push", "side": "side-push", "front-side": "side-push", "assembly": "assemble",
                    "front-assembly": "front-assemble", "front-side-assembly": "front-side-assemble",
                    "assembly-close": "assemble", "assembly-far": "assemble", "assembly-3": "assemble",
                    "assembly-4": "assemble"}
ASSEMBLY_LAYOUTS_UM = {"assembly-close": ((0, 0), (450, 0)), "assembly-far": ((0, 0), (900, 0)),
                       "assembly-3": ((0, 0), (420, -20), (190, 360)),
                       "assembly-4": ((0, 0), (400, 150), (800, -50), (1150, 200))}
"""Sphere centres (µm from the first sphere of :meth:`Scene.default`) of the multi-sphere set-ups beyond the paper
(docs/push-control.md §8): a pair 450 and 900 µm apart (the paper's is 600 µm), three spheres 407-444 µm apart,
four in a rough zig-zag."""


@dataclass(frozen=True)
class Experiment:
    """One controller in one of the paper's set-ups (§VI), picklable for process pools.

    Attributes
    ----------
    kind : {"front", "side", "front-side", "assembly", "front-assembly", "front-side-assembly", "assembly-close", \
"assembly-far", "assembly-3", "assembly-4"}
        Set-up: front push (§V-A), side push (§V-B), the side push on the front push's set-up, side-push
        assembly (§V-C), the
        front-push assembly the paper shows failing (Fig 3), the paper's Fig 15 protocol
        (a front push, then side-push assembly), or the assemblies of 2-4 spheres of :data:`ASSEMBLY_LAYOUTS_UM`.
    task : dict
        Options of :func:`controller` (push-task gains, model, fixed gap, ``servo`` …); what is
        not given is the default every controller uses, on the rig too.
    max_frames : int
        Frames after which a still-running trial is cut off.
    variability : Variability
    label : str
        Controller label for figures and tables.
    """

    kind: str
    task: dict = field(default_factory=dict)
    max_frames: int = 3000
    variability: Variability = Variability()
    label: str = ""


def geometry(kind: str) -> dict:
    """Start positions and goal of the paper's set-ups (§VI), in metres.

    The robot and the (first) sphere are :meth:`Scene.default`'s (``models/rig.toml [scene]``: the robot 1 mm
    behind the sphere, near the middle of the camera field). Front push: goal 750 µm beyond the sphere;
    side push: 300 µm from it, square to the robot's line (both :func:`default_goal`); ``front-side``: the
    side-push task (with its front push first) on the front push's set-up.
    Assembly: a second sphere 600 µm (centre to centre) ahead of the first; the goal is it. The
    set-ups beyond the paper place their spheres by :data:`ASSEMBLY_LAYOUTS_UM` (no goal).
    """
    if kind not in EXPERIMENT_TASKS:
        raise MagctlError(f"experiment kind {kind!r} is not one of {', '.join(EXPERIMENT_TASKS)}")
    layout = Scene.default(1)
    robot, sphere = layout.robot, layout.spheres[0]
    if kind in ("front", "side", "front-side"):   # front-side: the side-push task on the front push's set-up
        setup = "front-push" if kind == "front-side" else EXPERIMENT_TASKS[kind]
        return {"spheres": sphere[None], "robot": robot, "goal": default_goal(setup, robot, sphere[None])}
    if kind in ASSEMBLY_LAYOUTS_UM:
        return {"spheres": sphere + np.asarray(ASSEMBLY_LAYOUTS_UM[kind], float) * UM, "robot": robot, "goal": None}
    second = sphere + (600 * UM, 0.0)
    return {"spheres": np.stack([sphere, second]), "robot": robot, "goal": second}


def experiment_controller(exp: Experiment) -> Diagram:
    """The controller of ``exp``: :func:`controller` for its task, goal and options."""
    g = geometry(exp.kind)
    task = EXPERIMENT_TASKS[exp.kind]
    goal = g["goal"] if task in ("front-push", "side-push") else None
    return controller(task, n_spheres=len(g["spheres"]), goal=goal, **exp.task)


def push_loop(exp: Experiment) -> Diagram:
    """The closed-loop diagram of one experiment: its controller and the physical plant of its set-up."""
    g = geometry(exp.kind)
    scene = Scene(robot=g["robot"], spheres=g["spheres"])
    return closed_loop(experiment_controller(exp), plant(scene, exp.variability), name=f"{exp.kind}_push_loop")
