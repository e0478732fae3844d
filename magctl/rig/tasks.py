"""Rig tasks: a registry from task names to controller diagrams, and the B = 1 controller that steps them.

A task diagram's exported inputs are a subset of the observation's signals
(``robot_est`` (2,) m, ``heading_est`` rad, ``spheres_est`` (N, 2) m, ``lost``)
and its exported outputs include the drive's field command (``b_static`` (2,) T,
``b_osc`` T, ``freq`` 1/s) and a ``status`` code (:data:`STATUS_NAMES`).

Tasks register themselves with :func:`register_task`: ``goto``, ``patrol``, and
``front-push``, ``side-push``, ``assemble`` from ``magctl.control.push``, each
behind ``magctl.control.servo.Servo``, the rig's tracking guard and
``magctl.plant.drive.Drive``. A builder receives the first observation (to resolve defaults such
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
from magctl.control.guards import (
    DONE,
    FAILED,
    LOST,
    RUNNING,
    STATUS_NAMES,
    ArrivalStatus,
    Patrol,
    Tee,
    TrackingGuard,
)
from magctl.core.diagram import Diagram
from magctl.core.errors import MagctlError
from magctl.core.linear import Constant
from magctl.rig.interface import Command, Observation

OBS_SIGNALS = ("robot_est", "heading_est", "spheres_est", "lost")
COMMAND_SIGNALS = ("b_static", "b_osc", "freq")

__all__ = ["DONE", "FAILED", "LOST", "RUNNING", "STATUS_NAMES", "Controller", "Task", "TaskError", "available_tasks",
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
        Status codes that end the run → (exit status, reason). The defaults are the goto/patrol codes;
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


# --- options ---------------------------------------------------------------------------------------------
def _xy(options: dict, name: str, default_m) -> np.ndarray:
    """Option ``name`` as a point in m: from ``name_m`` (exact, as logged) or ``name_um`` (as typed)."""
    for key, scale in ((f"{name}_m", 1.0), (f"{name}_um", 1e-6)):
        v = options.get(key)
        if v is None:
            continue
        try:
            arr = np.asarray(v, dtype=float).reshape(-1)
        except (TypeError, ValueError):
            arr = np.full(0, np.nan)
        if arr.shape != (2,) or not np.all(np.isfinite(arr)):
            raise TaskError(f"option {key} must be two finite numbers, got {v!r}")
        return arr * scale
    return np.asarray(default_m, dtype=float)


def _num(options: dict, name: str, si_unit: str, user_unit: str, scale: float, default: float,
         positive: bool = True) -> float:
    """Option ``name`` in SI: from ``name_<si_unit>`` (exact, as logged) or ``name_<user_unit>`` (as typed)."""
    for key, k in ((f"{name}_{si_unit}", 1.0), (f"{name}_{user_unit}", scale)):
        if options.get(key) is None:
            continue
        try:
            v = float(options[key]) * k
        except (TypeError, ValueError):
            raise TaskError(f"option {key} must be a number, got {options[key]!r}") from None
        if not np.isfinite(v) or (positive and v <= 0):
            raise TaskError(f"option {key} must be {'positive' if positive else 'finite'}, got {options[key]!r}")
        return v
    return float(default)


def _float(options: dict, name: str, default: float) -> float:
    v = options.get(name, default)
    try:
        v = float(v)
    except (TypeError, ValueError):
        raise TaskError(f"option {name} must be a number, got {v!r}") from None
    if not np.isfinite(v):
        raise TaskError(f"option {name} must be finite, got {v!r}")
    return v


# --- the servo → guard → drive chain shared by every task ------------------------------------------------
def _servo_drive(params: Params, options: dict, resolved: dict, speed_cap: bool) -> tuple[list, list]:
    """The PI servo (``models/servo.toml``, setting ``servo``), the tracking guard and the drive.

    The servo holds its integral while tracking is lost (``hold``) and the guard zeroes the speed, so
    the drive commands no oscillation: the robot stops instead of driving blind.
    """
    from magctl.control.servo import Servo, servo_params
    from magctl.plant.drive import Drive

    setting = str(options.get("servo", params.tasks.servo_setting))
    sp = servo_params(setting)
    v_max = _num(options, "speed_max", "m_s", "um_s", 1e-6, sp.speed_max)
    resolved |= {"servo": setting, "speed_max_m_s": v_max}
    servo = Servo("servo", params=sp, speed_max=v_max, speed_cap_input=speed_cap, hold_input=True)
    blocks = [servo, TrackingGuard("guard"), Drive("drive"), Tee("robot_in", (2,), "m"),
              Tee("lost_in", (), "1", "bool")]
    wires = [("robot_in.y", "servo.robot_est"), ("lost_in.y", "servo.hold"), ("lost_in.y", "guard.lost"),
             ("servo.speed", "guard.speed"), ("guard.speed", "drive.speed"), ("servo.heading", "drive.heading")]
    return blocks, wires


COMMAND_OUTPUTS = {"b_static": "drive.b_static", "b_osc": "drive.b_osc", "freq": "drive.freq",
                   "stopped": "guard.stopped"}
OBS_INPUTS = {"robot_est": "robot_in.u", "lost": "lost_in.u"}


# --- built-in tasks ---------------------------------------------------------------------------------------
@register_task("goto")
def _goto(first_obs: Observation, options: dict, params: Params) -> Task:
    """Servo the robot to ``target`` (default: where it is) and stop there: DONE on arrival."""
    target = _xy(options, "target", first_obs.robot_est)
    resolved = {"target_m": target.tolist()}
    blocks, wires = _servo_drive(params, options, resolved, speed_cap=False)
    d = Diagram(
        "goto",
        [Constant("target", target, shape=(2,), unit="m"), *blocks, ArrivalStatus("status")],
        connections=[("target.y", "servo.target"), *wires, ("servo.arrived", "status.arrived"),
                     ("lost_in.y", "status.lost")],
        inputs=OBS_INPUTS, outputs={**COMMAND_OUTPUTS, "status": "status.status"},
    )
    return Task("goto", d, resolved)


@register_task("patrol")
def _patrol(first_obs: Observation, options: dict, params: Params) -> Task:
    """Drive round a square of side ``side`` (default 1 mm) starting at the robot, forever."""
    side = _num(options, "side", "m", "um", 1e-6, 1e-3)
    r0 = _xy(options, "origin", first_obs.robot_est)
    square = r0 + side * np.array([[0.0, 1.0], [-1.0, 1.0], [-1.0, 0.0], [0.0, 0.0]])
    resolved = {"side_m": side, "origin_m": r0.tolist()}
    blocks, wires = _servo_drive(params, options, resolved, speed_cap=False)
    tol = 2.0 * blocks[0].arrive_tol
    d = Diagram(
        "patrol",
        [Patrol("patrol", square, tol), *blocks],
        connections=[("robot_in.y", "patrol.robot_est"), ("patrol.target", "servo.target"), *wires],
        inputs=OBS_INPUTS, outputs={**COMMAND_OUTPUTS, "status": "patrol.status", "lap": "patrol.lap"},
    )
    return Task("patrol", d, resolved)


def _push_outcomes() -> tuple[dict, dict]:
    from magctl.control import push

    outcomes = {push.CONVERGED: ("done", "converged: the sphere is within ε_p of the goal"),
                push.ATTEMPT_LIMIT: ("failed", "attempt limit reached"),
                push.TRACKING_LOST: ("tracking-lost", "the task stopped on tracking loss"),
                push.SPHERE_LOST: ("failed", "sphere lost"),
                push.STALLED: ("failed", "a phase timed out (stalled)")}
    return outcomes, dict(push.STATUS_NAMES)


def _push_diagram(name: str, task_block, first_obs: Observation, options: dict, params: Params, resolved: dict):
    blocks, wires = _servo_drive(params, options, resolved, speed_cap=True)
    outcomes, names = _push_outcomes()
    d = Diagram(
        name.replace("-", "_"),
        [task_block, *blocks],
        connections=[("robot_in.y", "push.robot_est"), ("lost_in.y", "push.lost"), ("push.target", "servo.target"),
                     ("push.speed_cap", "servo.speed_cap"), *wires],
        inputs={**OBS_INPUTS, "spheres_est": "push.spheres_est"},
        outputs={**COMMAND_OUTPUTS, "status": "push.status", "attempt": "push.attempt", "phase": "push.phase",
                 "correction": "push.correction", "target": "push.target"},
    )
    return Task(name, d, resolved, outcomes, names)


def _need_spheres(task: str, first_obs: Observation, n: int) -> int:
    have = first_obs.spheres_est.shape[0]
    if have < n:
        raise TaskError(f"{task} needs at least {n} tracked sphere(s); the rig reports {have}")
    return have


def _sphere_and_away(first_obs: Observation) -> tuple[np.ndarray, np.ndarray]:
    """Sphere 0's estimate and the unit vector from the robot to it (+x if they coincide)."""
    ps = first_obs.spheres_est[0]
    away = ps - first_obs.robot_est
    length = np.hypot(*away)
    return ps, (away / length if length > 0 else np.array([1.0, 0.0]))


@register_task("front-push")
def _front_push(first_obs: Observation, options: dict, params: Params) -> Task:
    """Front-push sphere 0 to ``goal`` (default ``tasks.goal_distance`` beyond it, away from the robot), §V-A."""
    from magctl.control.push.front import FrontPushTask

    n = _need_spheres("front-push", first_obs, 1)
    ps, away = _sphere_and_away(first_obs)
    goal = _xy(options, "goal", ps + params.tasks.goal_distance * away)
    kc = _float(options, "kc", 1.0)
    delta0 = _num(options, "delta0", "m", "um", 1e-6, 0.0, positive=False)
    push_speed = _num(options, "push_speed", "m_s", "um_s", 1e-6, 0.4e-3)
    travel_speed = _num(options, "travel_speed", "m_s", "um_s", 1e-6, 1.0e-3)
    resolved = {"goal_m": goal.tolist(), "kc": kc, "delta0_m": delta0, "push_speed_m_s": push_speed,
                "travel_speed_m_s": travel_speed}
    try:
        block = FrontPushTask("push", goal=goal, kc=kc, delta0=delta0, n_spheres=n, push_speed=push_speed,
                              travel_speed=travel_speed)
    except MagctlError as err:
        raise TaskError(f"front-push: {err}") from None
    return _push_diagram("front-push", block, first_obs, options, params, resolved)


@register_task("side-push")
def _side_push(first_obs: Observation, options: dict, params: Params) -> Task:
    """Side-push sphere 0 to ``goal`` (default 300 µm beyond it, away from the robot; §VI), §V-B."""
    from magctl.control.push.side import SidePushTask

    n = _need_spheres("side-push", first_obs, 1)
    ps, away = _sphere_and_away(first_obs)
    goal = _xy(options, "goal", ps + params.tasks.side_goal_distance * away)
    ks = _float(options, "ks", 0.9)
    model = str(options.get("model", "lin"))
    resolved = {"goal_m": goal.tolist(), "ks": ks, "model": model}
    try:
        block = SidePushTask("push", goal=goal, ks=ks, model=model, n_spheres=n)
    except MagctlError as err:
        raise TaskError(f"side-push: {err}") from None
    return _push_diagram("side-push", block, first_obs, options, params, resolved)


@register_task("assemble")
def _assemble(first_obs: Observation, options: dict, params: Params) -> Task:
    """Assemble sphere 0 onto sphere 1 by side-pushing along the adjusted line (§V-C, eq 21)."""
    from magctl.control.push.assembly import AssemblyTask

    n = _need_spheres("assemble", first_obs, 2)
    theta = _num(options, "theta_n", "rad", "deg", np.pi / 180.0, np.deg2rad(30.0), positive=False)
    ks = _float(options, "ks", 0.9)
    resolved = {"theta_n_rad": theta, "ks": ks}
    try:
        block = AssemblyTask("push", n_spheres=n, theta_n=theta, ks=ks)
    except MagctlError as err:
        raise TaskError(f"assemble: {err}") from None
    return _push_diagram("assemble", block, first_obs, options, params, resolved)
