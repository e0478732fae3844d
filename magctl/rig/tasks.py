"""Rig tasks: a registry from task names to controller diagrams, and the B = 1 controller that steps them.

A task diagram's exported inputs are a subset of the observation's signals
(``robot_est`` (2,) m, ``heading_est`` rad, ``spheres_est`` (N, 2) m, ``lost``)
and its exported outputs include the drive's field command (``b_static`` (2,) T,
``b_osc`` T, ``freq`` 1/s) and a ``status`` code (:data:`STATUS_NAMES`).

Tasks register themselves with :func:`register_task`; ``front-push``,
``side-push`` and ``assemble`` built from ``magctl.control.push`` plug in the
same way. A builder receives the first observation (to resolve defaults such
as the goal) and the user's options, and returns a :class:`Task` whose
``options`` are fully resolved — they go into the run log so that a replay
rebuilds the identical controller.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from magctl.config import Params, load_model
from magctl.core.diagram import Diagram
from magctl.core.errors import MagctlError
from magctl.core.linear import Constant
from magctl.rig.interface import Command, Observation
from magctl.rig.standin_control import (
    DONE,
    FAILED,
    RUNNING,
    STATUS_NAMES,
    ArrivalStatus,
    Patrol,
    StandinDrive,
    StandinFrontPush,
    StandinServo,
    Tee,
    TrackingGuard,
)

OBS_SIGNALS = ("robot_est", "heading_est", "spheres_est", "lost")
COMMAND_SIGNALS = ("b_static", "b_osc", "freq")

__all__ = ["DONE", "FAILED", "RUNNING", "STATUS_NAMES", "Controller", "Task", "TaskError", "available_tasks",
           "build_task", "register_task"]


class TaskError(MagctlError):
    """Unknown task, bad task options, or a task diagram that breaks the contract."""


@dataclass
class Task:
    """A controller for the rig.

    Attributes
    ----------
    name : str
        Registry name (``goto``, ``front-push`` …).
    diagram : Diagram
        Inputs ⊆ :data:`OBS_SIGNALS`; outputs ⊇ :data:`COMMAND_SIGNALS` and ``status``.
    options : dict
        Resolved options (JSON-able, SI in ``_m``-suffixed keys so that they round-trip exactly);
        rebuilding with them gives the same task.
    outcomes : dict of int to (str, str)
        Status codes that end the run → (exit status, reason). The defaults are the stand-in codes;
        tasks with other codes (e.g. ``magctl.control.push``'s ``sphere_lost``, ``stalled``) list theirs.
    status_names : dict of int to str
        Names of the status codes, for logs and summaries.
    """

    name: str
    diagram: Diagram
    options: dict[str, Any] = field(default_factory=dict)
    outcomes: dict[int, tuple[str, str]] = field(
        default_factory=lambda: {DONE: ("done", "task completed"), FAILED: ("failed", "task gave up")})
    status_names: dict[int, str] = field(default_factory=lambda: dict(STATUS_NAMES))

    def __post_init__(self):
        d = self.diagram
        extra = [n for n in d.inputs if n not in OBS_SIGNALS]
        missing = [n for n in (*COMMAND_SIGNALS, "status") if n not in d.outputs]
        if extra or missing:
            raise TaskError(f"task {self.name!r}: diagram inputs {extra} are not observation signals "
                            f"{list(OBS_SIGNALS)}; missing outputs {missing}")


Builder = Callable[[Observation, dict, Params], Task]
_REGISTRY: dict[str, Builder] = {}


def register_task(name: str):
    """Decorator: ``@register_task("side-push")`` on ``builder(first_obs, options, params) -> Task``."""

    def deco(fn: Builder) -> Builder:
        _REGISTRY[name] = fn
        return fn

    return deco


def available_tasks() -> list[str]:
    return sorted(_REGISTRY)


def build_task(name: str, first_obs: Observation, options: dict | None = None, params: Params | None = None) -> Task:
    """Build task ``name`` for a rig whose first observation is ``first_obs``."""
    try:
        builder = _REGISTRY[name]
    except KeyError:
        raise TaskError(f"unknown task {name!r}; available: {', '.join(available_tasks())}") from None
    return builder(first_obs, dict(options or {}), params or load_model("rig"))


class Controller:
    """A task diagram stepped with B = 1, one frame per observation.

    ``step(obs)`` returns the field command and the task's other outputs; ``reset()``
    restores the initial state (the runtime calls it on every activation).
    """

    def __init__(self, task: Task, seed: int = 0):
        self.task, self.seed = task, seed
        self.diagram = task.diagram
        self._inputs = list(self.diagram.inputs)
        self.reset()

    def reset(self) -> None:
        self.state = self.diagram.initial_state(1, seed=self.seed)

    def step(self, obs: Observation) -> tuple[Command, dict[str, np.ndarray]]:
        signals = obs.controller_inputs()
        u = {n: signals[n] for n in self._inputs}
        outs, self.state = self.diagram.step(self.state, u)
        cmd = Command(np.array(outs["b_static"][0], dtype=float), float(outs["b_osc"][0]), float(outs["freq"][0]))
        return cmd, outs


# --- built-in tasks ------------------------------------------------------------------------------------
def _xy(options: dict, name: str, default_m) -> np.ndarray:
    """Option ``name`` as a point in m: from ``name_m`` (exact, as logged) or ``name_um`` (as typed)."""
    for key, scale in ((f"{name}_m", 1.0), (f"{name}_um", 1e-6)):
        v = options.get(key)
        if v is None:
            continue
        arr = np.asarray(v, dtype=float).reshape(-1)
        if arr.shape != (2,) or not np.all(np.isfinite(arr)):
            raise TaskError(f"option {key} must be two finite numbers, got {v!r}")
        return arr * scale
    return np.asarray(default_m, dtype=float)


def _servo_drive(params: Params) -> tuple[list, list]:
    s, dr, sd, lim = params.servo, params.drive, params.standin, params.limits
    blocks = [
        StandinServo("servo", s.kp, s.speed_max, s.arrive_tol),
        TrackingGuard("guard"),
        StandinDrive("drive", dr.b_static, dr.freq, sd.step_per_cycle_at_max, lim.b_osc_max, lim.b_osc_max),
    ]
    wires = [("servo.speed", "guard.speed"), ("guard.speed", "drive.speed"), ("servo.heading", "drive.heading")]
    return blocks, wires


@register_task("goto")
def _goto(first_obs: Observation, options: dict, params: Params) -> Task:
    """Servo the robot to ``target_um`` and stop there (status DONE on arrival)."""
    target = _xy(options, "target", first_obs.robot_est)
    blocks, wires = _servo_drive(params)
    arrived = ArrivalStatus("status")
    d = Diagram(
        "goto",
        [Constant("target", target, shape=(2,), unit="m"), *blocks, arrived],
        connections=[("target.y", "servo.target"), *wires, ("servo.arrived", "status.arrived"),
                     ("guard.stopped", "status.lost")],
        inputs={"robot_est": "servo.robot_est", "lost": "guard.lost"},
        outputs={"b_static": "drive.b_static", "b_osc": "drive.b_osc", "freq": "drive.freq",
                 "status": "status.status", "stopped": "guard.stopped"},
    )
    return Task("goto", d, {"target_m": target.tolist()})


@register_task("patrol")
def _patrol(first_obs: Observation, options: dict, params: Params) -> Task:
    """Drive round a square of side ``side_um`` (default 1 mm) starting at the robot, forever."""
    side = float(options.get("side_m", float(options.get("side_um", 1000.0)) * 1e-6))
    if not np.isfinite(side) or side <= 0:
        raise TaskError(f"patrol: side must be a positive length, got {side!r} m")
    r0 = _xy(options, "origin", first_obs.robot_est)
    square = r0 + side * np.array([[1.0, 0.0], [1.0, 1.0], [0.0, 1.0], [0.0, 0.0]])
    blocks, wires = _servo_drive(params)
    tees = [Tee("robot_in", (2,), "m")]
    d = Diagram(
        "patrol",
        [*tees, Patrol("patrol", square, 1.5 * params.servo.arrive_tol), *blocks],
        connections=[("robot_in.y", "patrol.robot_est"), ("robot_in.y", "servo.robot_est"),
                     ("patrol.target", "servo.target"), *wires],
        inputs={"robot_est": "robot_in.u", "lost": "guard.lost"},
        outputs={"b_static": "drive.b_static", "b_osc": "drive.b_osc", "freq": "drive.freq",
                 "status": "patrol.status", "lap": "patrol.lap", "stopped": "guard.stopped"},
    )
    return Task("patrol", d, {"side_m": side, "origin_m": r0.tolist()})


@register_task("front-push")
def _front_push(first_obs: Observation, options: dict, params: Params) -> Task:
    """Front-push sphere 0 to ``goal_um`` (default: ``goal_distance`` beyond it, away from the robot)."""
    n = first_obs.spheres_est.shape[0]
    if n < 1:
        raise TaskError("front-push needs at least one tracked sphere; the rig reports none")
    fp, sd = params.front_push, params.standin
    ps, pr = first_obs.spheres_est[0], first_obs.robot_est
    away = ps - pr
    away = away / np.hypot(*away) if np.hypot(*away) > 0 else np.array([1.0, 0.0])
    goal = _xy(options, "goal", ps + fp.goal_distance * away)
    kc = float(options.get("kc", fp.kc))
    delta0 = _xy(options, "delta0", np.zeros(2))
    push = StandinFrontPush("push", n, goal, kc=kc, delta0=delta0, eps_p=fp.eps_p,
                            contact=sd.robot_contact_radius + sd.sphere_radius, gap=fp.approach_gap,
                            retreat=fp.retreat, tol=1.5 * params.servo.arrive_tol,
                            max_attempts=int(fp.max_attempts))
    blocks, wires = _servo_drive(params)
    # tees fan one observation signal out to several blocks
    tees = [Tee("robot_in", (2,), "m"), Tee("lost_in", (), "1", "bool")]
    d = Diagram(
        "front_push",
        [*tees, push, *blocks],
        connections=[("robot_in.y", "push.robot_est"), ("robot_in.y", "servo.robot_est"),
                     ("lost_in.y", "push.lost"), ("lost_in.y", "guard.lost"), ("push.target", "servo.target"),
                     *wires],
        inputs={"robot_est": "robot_in.u", "spheres_est": "push.spheres_est", "lost": "lost_in.u"},
        outputs={"b_static": "drive.b_static", "b_osc": "drive.b_osc", "freq": "drive.freq",
                 "status": "push.status", "attempt": "push.attempt", "target": "push.target",
                 "stopped": "guard.stopped"},
    )
    return Task("front-push", d, {"goal_m": goal.tolist(), "kc": kc, "delta0_m": delta0.tolist()})
