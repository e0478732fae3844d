"""Rig tasks: a registry from task names to the controllers of :func:`magctl.loops.controller`, and the B = 1
controller that steps them.

A task's diagram is :func:`magctl.loops.controller` itself — the diagram the studies run — built
from the first observation (to resolve defaults such as the goal) and the user's options; the
open-loop ``identify`` sweep, which has no servo and no drive, is its one block
(:class:`~magctl.control.excitation.Excitation`) alone. Its
exported inputs are a subset of the observation's signals (``robot_est`` (2,) m, ``spheres_est``
(N, 2) m, ``lost``) and its exported outputs include the field command (``b_static`` (2,) T,
``b_osc`` T, ``freq`` 1/s) and a ``status`` (:class:`~magctl.control.status.Status`).

Options are the controller's: for the push tasks every parameter of ``models/push.toml`` that
the task uses (``eps_um``, ``clearance_um``, ``kc``, ``max_attempts`` …) plus ``goal``, for
every task but ``identify`` ``servo`` (a setting of ``models/servo.toml``) and ``speed_max``; for
``identify`` (the open-loop speed sweep of :mod:`magctl.control.excitation`) its times and distances
(``hold_s``, ``pause_s``, ``segment_s``, ``side_max_um``: ``models/identify.toml``; ``clearance_um``:
``models/push.toml [common]``).
A length, speed or time is given with its unit in the key (``goal_um``, ``push_speed_um_s``; any unit suffix of
:data:`magctl.config.UNITS` of the right kind); an unknown key is an error. The resolved options
(every parameter, SI, in ``_m``/``_m_s``/``_rad``/``_s``-suffixed keys so that they round-trip exactly)
go into the run log, so that a replay rebuilds the identical controller.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from magctl.config import UNITS, Params, load_model, split_unit
from magctl.control.arrangement import ARRANGEMENTS
from magctl.control.assembly_planner import PLANNERS
from magctl.control.excitation import Excitation, ExcitationParams, inside_field
from magctl.control.push_params import (
    DIRT_RESPONSES,
    FRONT_LEARNING,
    SIDE_LEARNING,
    AssemblyParams,
    FrontParams,
    PlannedParams,
    SideParams,
)
from magctl.control.servo import default_servo_setting, servo_params, servo_settings
from magctl.control.side_models import SIDE_MODELS
from magctl.control.status import STATUS_NAMES, Status
from magctl.core.compiled import NotCompilable
from magctl.core.diagram import Diagram
from magctl.core.errors import MagctlError
from magctl.core.simulation import ENGINES
from magctl.loops import COMMAND, OBSERVATION, controller, default_goal, sphere_count
from magctl.rig.interface import Command, CommandRejected, Observation, RigLimits
from magctl.sensing.camera import field_of_view, outside_view

OBS_SIGNALS = OBSERVATION
COMMAND_SIGNALS = COMMAND

__all__ = ["Controller", "Task", "TaskError", "available_tasks", "build_task", "register_task", "task_options"]


class TaskError(MagctlError):
    """Unknown task, bad task options, or a task diagram that breaks the contract."""


PUSH_OUTCOMES = {Status.CONVERGED: ("done", "converged: the sphere is within ε_p of the goal"),
                 Status.ATTEMPT_LIMIT: ("failed", "attempt limit reached"),
                 Status.TRACKING_LOST: ("tracking-lost", "the task stopped on tracking loss"),
                 Status.SPHERE_LOST: ("failed", "sphere lost"),
                 Status.STALLED: ("failed", "a phase timed out (stalled)")}
IDENTIFY_OUTCOMES = {Status.CONVERGED: ("done", "the sweep completed"),
                     Status.STALLED: ("failed", "safety stop: the robot came within the clearance of a sphere or "
                                                "within the margin of the camera field's edge; coils zeroed"),
                     Status.TRACKING_LOST: ("tracking-lost", "tracking lost during the open-loop sweep; coils zeroed")}


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
        Resolved options (JSON-able, SI in unit-suffixed keys so that they round-trip exactly);
        rebuilding with them gives the same task.
    outcomes : dict of int to (str, str)
        Status codes that end the run → (exit status, reason).
    status_names : dict of int to str
        Names of the status codes, for logs and summaries.
    """

    name: str
    diagram: Diagram
    options: dict[str, Any] = field(default_factory=dict)
    outcomes: dict[int, tuple[str, str]] = field(
        default_factory=lambda: {Status.CONVERGED: ("done", "task completed")})
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
    """Decorator: ``@register_task("name")`` on ``builder(first_obs, options, params) -> Task``."""

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
    restores the initial state (the runtime calls it on every activation). With ``engine``
    ``"compiled"`` or ``"auto"`` a diagram whose blocks all have kernels runs as one compiled call
    per frame (:meth:`magctl.core.compiled.CompiledDiagram.stepper`), with the same commands.

    A block's Python event (its planner: docs/core.md "Python events") runs at the end of the frame that
    raised it, as in a study — unless ``defer_events``: then the frame only records an
    :class:`~magctl.core.kernel.EventRequest` (:meth:`take_requests`), the block's flag stays up and its frames
    hold the robot, and the caller runs ``request.run()`` where it likes (the runtime: on a worker thread) and
    merges the result with :meth:`apply` before a later frame (docs/rig.md "Planning off the frame").
    :attr:`frames` counts the steps since the last reset; ``request.tick`` is the frame that raised it.
    """

    def __init__(self, task: Task, seed: int = 0, engine: str = "auto", *, defer_events: bool = False):
        if engine not in ENGINES:
            raise TaskError(f"engine {engine!r} is not one of {', '.join(ENGINES)}")
        self.task, self.seed, self.engine = task, seed, engine
        self.diagram = task.diagram
        self._inputs = list(self.diagram.inputs)
        self._compiled = None
        if engine != "interpreted":
            try:
                self._compiled = self.diagram.compile()
            except NotCompilable:
                if engine == "compiled":
                    raise
        self.defer_events = bool(defer_events)
        leaves = self.diagram.schedule.leaves
        # the leaves whose kernel raises a Python event, by block
        self._event_leaves = {id(lf.block): i for i, lf in enumerate(leaves)
                              if lf.block.kernel_driver() is not None and lf.block.kernel_driver().flag >= 0}
        self._requests: list = []
        self._outstanding: dict[int, object] = {}
        self.frames = 0
        self.reset()

    @property
    def has_events(self) -> bool:
        """Whether some block of the task raises a Python event (the planned assembly's plan)."""
        return bool(self._event_leaves)

    @property
    def compiled(self) -> bool:
        """Whether frames run as one compiled call."""
        return self._compiled is not None

    def reset(self) -> None:
        state = self.diagram.initial_state(1, seed=self.seed)
        self._stepper = None if self._compiled is None else self._compiled.stepper(state, 1)
        self._state = state
        self.frames = 0
        self._requests = []
        self._outstanding = {}   # a reset drops the pending events: their results are never applied
        defer = self._defer if self.defer_events else None
        if self._stepper is not None:
            self._stepper.defer = defer
        for i in self._event_leaves.values():
            driver = self.diagram.schedule.leaves[i].block.kernel_driver()
            driver.forget_events()
            driver.defer = defer if self._stepper is None else None

    def _defer(self, request) -> None:
        request.tick = self.frames
        self._requests.append(request)
        self._outstanding[id(request)] = request

    @property
    def pending(self) -> list:
        """The deferred events whose results are not applied yet (their blocks' frames hold the robot)."""
        return list(self._outstanding.values())

    def take_requests(self) -> list:
        """The events the frames since the last call raised, to run off the frame (``defer_events``); each is
        pending until :meth:`apply` merges its result."""
        out, self._requests = self._requests, []
        return out

    def apply(self, request, result: dict) -> None:
        """Merge a deferred event's result (``request.run()``) into the controller's state, before the next
        frame: what the handler changed takes its values, the rest keeps what the frames since the request gave
        it (:func:`magctl.core.kernel.merge_event`). A request from before the last :meth:`reset` is refused."""
        if self._outstanding.pop(id(request), None) is not request:
            raise TaskError("apply: this event is not pending on the controller (applied already, or raised before "
                            "a reset)")
        if self._stepper is not None:
            self._stepper.apply_event(request, result)
            return
        i = self._event_leaves[id(request.block)]
        leaves = list(self._state["leaves"])
        leaves[i] = request.block.kernel_driver().apply_event(leaves[i], request, result)
        self._state = {**self._state, "leaves": leaves}

    @property
    def state(self) -> dict:
        """The controller's state after the last frame."""
        return self._state if self._stepper is None else self._stepper.state

    def step(self, obs: Observation) -> tuple[Command, dict[str, np.ndarray]]:
        if self._stepper is not None:
            obs.write_inputs(self._stepper.inputs)
            outs = self._stepper.step_in_place()
        else:
            signals = obs.controller_inputs()
            outs, self._state = self.diagram.step(self._state, {n: signals[n] for n in self._inputs})
        self.frames += 1
        cmd = Command(np.array(outs["b_static"][0], dtype=float), float(outs["b_osc"][0]), float(outs["freq"][0]))
        return cmd, outs


# --- options ---------------------------------------------------------------------------------------------
_PLANNED = "assemble (planned)"
"""The options of ``assemble`` when it plans its passes (:class:`~magctl.control.push.planned.PlannedAssemblyTask`)."""
_SI_SUFFIX = {"m": "m", "m/s": "m_s", "rad": "rad", "s": "s", "1": "", "": ""}
_PUSH_RECORDS = {"front-push": FrontParams, "side-push": SideParams, "assemble": AssemblyParams,
                 "front-side-assemble": AssemblyParams, _PLANNED: PlannedParams}
"""Each push task's parameter record (:mod:`magctl.control.push_params`): its fields are the task's options."""
_OPTIONAL = {"front-push": {}, "side-push": {"fixed_gap": "m"},
             "assemble": {"fixed_gap": "m", "n_spheres": "1", "arrangement": "", "planner": "", "plan_frames": "1"},
             "front-side-assemble": {"fixed_gap": "m", "front_attempts": "1"},
             _PLANNED: {"n_spheres": "1", "arrangement": "", "planner": "", "plan_frames": "1"}}


def task_options(task: str) -> dict[str, tuple[Any, str]]:
    """Options of rig task ``task``: name → (default, SI unit); a default of None means "not set"."""
    common = {"servo": (default_servo_setting(), ""), "speed_max": (None, "m/s")}
    if task == "goto":
        return {"target": (None, "m"), **common}
    if task == "patrol":
        return {"side": (1e-3, "m"), "origin": (None, "m"), **common}
    if task == "identify":
        defaults = ExcitationParams.resolve()
        return {name: (getattr(defaults, name), "s" if name in ("hold", "pause", "segment") else "m")
                for name in ExcitationParams.OPTIONS}
    spec = _PUSH_RECORDS[task].spec()
    if task in ("front-push", "side-push"):
        spec["goal"] = (None, "m")
    spec |= {k: (None, unit) for k, unit in _OPTIONAL[task].items()}
    return spec | common


def resolve_options(task: str, options: dict) -> dict[str, Any]:
    """``options`` as typed (any unit suffix) → option name → SI value, with clear errors; unknown keys refused."""
    spec = task_options(task)
    values: dict[str, Any] = {}
    for key, raw in options.items():
        name, factor = _option_name(task, key, spec)
        if name in values:
            raise TaskError(f"{task}: option {name!r} given twice")
        values[name] = _option_value(task, key, raw, factor, spec[name][1], name)
    return values


def _option_name(task: str, key: str, spec: dict) -> tuple[str, float]:
    if key in spec:
        return key, 1.0
    base, suffix = split_unit(key)
    if suffix is not None and base in spec:
        si_unit, factor = UNITS[suffix]
        want = spec[base][1]
        if si_unit != want:
            raise TaskError(f"{task}: option {key} is in {si_unit!r} but {base} is a quantity in {want!r}")
        return base, factor
    names = ", ".join(f"{n}_{_SI_SUFFIX.get(u, u)}" if _SI_SUFFIX.get(u) else n for n, (_, u) in sorted(spec.items()))
    raise TaskError(f"{task}: unknown option {key!r}; options: {names}")


def _option_value(task: str, key: str, raw, factor: float, unit: str, name: str):
    if name == "servo":
        if raw not in servo_settings():
            raise TaskError(f"{task}: option servo={raw!r} is not one of {', '.join(servo_settings())}")
        return str(raw)
    if name == "model":
        if raw not in SIDE_MODELS:
            raise TaskError(f"{task}: option model={raw!r} is not one of {', '.join(SIDE_MODELS)}")
        return str(raw)
    learning = FRONT_LEARNING if task == "front-push" else SIDE_LEARNING
    for option, known in (("learning", learning), ("dirt_response", DIRT_RESPONSES), ("arrangement", ARRANGEMENTS),
                          ("planner", PLANNERS)):
        if name == option:
            if raw not in known:
                raise TaskError(f"{task}: option {option}={raw!r} is not one of {', '.join(known)}")
            return str(raw)
    if name in ("goal", "target", "origin"):
        try:
            arr = np.asarray(raw, dtype=float).reshape(-1)
        except (TypeError, ValueError):
            arr = np.full(0, np.nan)
        if arr.shape != (2,) or not np.all(np.isfinite(arr)):
            raise TaskError(f"{task}: option {key} must be two finite numbers, got {raw!r}")
        return arr * factor
    if isinstance(raw, bool):
        raise TaskError(f"{task}: option {key} must be a number, got {raw!r}")
    try:
        v = float(raw) * factor
    except (TypeError, ValueError):
        raise TaskError(f"{task}: option {key} must be a number, got {raw!r}") from None
    if not np.isfinite(v):
        raise TaskError(f"{task}: option {key} must be finite, got {raw!r}")
    if unit == "m/s" and v <= 0:
        raise TaskError(f"{task}: option {key} must be positive, got {raw!r}")
    if name.endswith(("_frames", "attempts")) or name == "n_spheres":
        if v != int(v) or v < 0:
            raise TaskError(f"{task}: option {key} must be a whole number >= 0, got {raw!r}")
        return int(v)
    return v


def _logged(values: dict[str, Any], spec: dict) -> dict[str, Any]:
    """Resolved options in unit-suffixed SI keys (JSON-able; parsed back by :func:`resolve_options`)."""
    out = {}
    for name, v in sorted(values.items()):
        if v is None:
            continue
        suffix = _SI_SUFFIX.get(spec[name][1], "")
        out[f"{name}_{suffix}" if suffix else name] = v.tolist() if isinstance(v, np.ndarray) else v
    return out


def check_in_field(task: str, points: dict[str, Any]) -> None:
    """Refuse a task whose target, goal or waypoints lie outside the camera's field of view (``models/camera.toml``):
    the robot would be driven out of sight, or told to push a sphere where it cannot be tracked."""
    w, h = span = field_of_view()
    for name, p in points.items():
        if p is None:
            continue
        p = np.atleast_2d(np.asarray(p, dtype=float))
        out = outside_view(p, span)
        if out.any():
            where = ", ".join(f"({x * 1e6:.6g}, {y * 1e6:.6g})" for x, y in p[out])
            raise TaskError(f"{task}: {name} {where} µm lies outside the camera's field of view "
                            f"[0, {w * 1e6:.0f}] × [0, {h * 1e6:.0f}] µm")


def check_options(task: str, options: dict) -> None:
    """What can be checked of a task's options before the rig is activated: each option resolves, and a given
    target, goal or origin lies inside the camera's field of view."""
    if task not in _REGISTRY:
        raise TaskError(f"unknown task {task!r}; available: {', '.join(available_tasks())}")
    given = resolve_options(task, options)
    check_in_field(task, {k: given[k] for k in ("target", "goal", "origin") if k in given})
    if task == "identify":
        _excitation_params(options)


def _resolved(task: str, options: dict) -> tuple[dict[str, Any], dict[str, Any]]:
    """(controller keyword values, logged options): defaults filled in, every option checked, and the points it
    names inside the camera's field of view."""
    spec = task_options(task)
    given = resolve_options(task, options)
    check_in_field(task, {k: given[k] for k in ("target", "goal", "origin") if k in given})
    values = {name: given.get(name, default) for name, (default, _unit) in spec.items()}
    if values["speed_max"] is None:
        values["speed_max"] = servo_params(values["servo"]).speed_max
    return values, _logged(values, spec)


def _need_spheres(task: str, first_obs: Observation) -> int:
    have = first_obs.spheres_est.shape[0]
    need = sphere_count(task)
    if have < need:
        raise TaskError(f"{task} needs at least {need} tracked sphere(s); the rig reports {have}")
    return have


def _build(task: str, values: dict, n_spheres: int, **extra) -> Diagram:
    try:
        return controller(task, n_spheres=n_spheres, **values, **extra)
    except MagctlError as err:
        raise TaskError(f"{task}: {err}") from None


# --- the tasks --------------------------------------------------------------------------------------------
@register_task("goto")
def _goto(first_obs: Observation, options: dict, params: Params) -> Task:
    """Servo the robot to ``target`` (default: where it is) and stop there: CONVERGED on arrival."""
    values, logged = _resolved("goto", options)
    if values["target"] is None:
        values["target"] = np.asarray(first_obs.robot_est, dtype=float)
        logged["target_m"] = values["target"].tolist()
    return Task("goto", _build("goto", values, 0), logged)


@register_task("patrol")
def _patrol(first_obs: Observation, options: dict, params: Params) -> Task:
    """Drive round a square of side ``side`` (default 1 mm) from the robot (or ``origin``) towards the middle of the
    camera field, first along y, then along x, forever."""
    values, logged = _resolved("patrol", options)
    side, origin = values.pop("side"), values.pop("origin")
    if side <= 0:
        raise TaskError("patrol: option side must be positive")
    if origin is None:
        origin = np.asarray(first_obs.robot_est, dtype=float)
        logged["origin_m"] = origin.tolist()
    sx, sy = np.where(origin < 0.5 * np.asarray(field_of_view()), 1.0, -1.0)
    square = origin + side * np.array([[0.0, sy], [sx, sy], [sx, 0.0], [0.0, 0.0]])
    check_in_field("patrol", {"waypoint": square})
    return Task("patrol", _build("patrol", values, 0, waypoints=square), logged,
                outcomes={})


def _push(task: str, first_obs: Observation, options: dict) -> Task:
    n = _need_spheres(task, first_obs)
    values, logged = _resolved(task, options)
    if "goal" in values and values["goal"] is None:
        values["goal"] = default_goal(task, first_obs.robot_est, first_obs.spheres_est)
        logged["goal_m"] = values["goal"].tolist()
        check_in_field(task, {"default goal": values["goal"]})
    return Task(task, _build(task, values, n), logged, dict(PUSH_OUTCOMES))


@register_task("front-push")
def _front_push(first_obs: Observation, options: dict, params: Params) -> Task:
    """Front-push sphere 0 to ``goal`` (default 750 µm beyond it, away from the robot), §V-A."""
    return _push("front-push", first_obs, options)


@register_task("side-push")
def _side_push(first_obs: Observation, options: dict, params: Params) -> Task:
    """Side-push sphere 0 to ``goal`` (default 300 µm from it, square to the robot's line), §V-B."""
    return _push("side-push", first_obs, options)


@register_task("assemble")
def _assemble(first_obs: Observation, options: dict, params: Params) -> Task:
    """Assemble the tracked spheres. Two, with no ``planner`` or ``arrangement`` option: sphere 0 onto sphere 1 by
    side-pushing along the adjusted line (§V-C, eq 21). Otherwise (``n_spheres`` = 2-4, the rig's tracked count):
    into ``arrangement`` (pair, line, triangle) by passes the ``planner`` chooses (optimal, greedy;
    docs/push-control.md §8)."""
    given = resolve_options("assemble", options)
    have = _need_spheres("assemble", first_obs)
    n = given.get("n_spheres", have)
    if n != have:
        raise TaskError(f"assemble: option n_spheres={n} but the rig tracks {have} sphere(s)")
    if n <= 2 and not given.keys() & {"planner", "arrangement"}:
        if "plan_frames" in given:
            raise TaskError("assemble: option plan_frames applies to the planned assembly only (3-4 spheres, or a "
                            "pair with a planner or arrangement option)")
        values, logged = _resolved("assemble", {k: v for k, v in options.items() if split_unit(k)[0] != "n_spheres"})
        values = {k: v for k, v in values.items() if k not in ("n_spheres", "arrangement", "planner", "plan_frames")}
        return Task("assemble", _build("assemble", values, n), logged, dict(PUSH_OUTCOMES))
    planned = task_options(_PLANNED)
    foreign = sorted(set(given) - set(planned))
    if foreign:
        raise TaskError(f"assemble: option(s) {', '.join(foreign)} do not apply to the planned assembly of "
                        f"{n} spheres; its options: {', '.join(planned)}")
    values, logged = _resolved(_PLANNED, options)
    values = {k: v for k, v in values.items() if k != "n_spheres"}
    if values["planner"] is None:
        values["planner"] = logged["planner"] = "optimal"
    if values["arrangement"] is None:
        values.pop("arrangement")
    logged |= {"n_spheres": n}
    return Task("assemble", _build("assemble", values, n), logged, dict(PUSH_OUTCOMES))


@register_task("front-side-assemble")
def _front_side_assemble(first_obs: Observation, options: dict, params: Params) -> Task:
    """The paper's Fig 15: front-push sphere 0 onto sphere 1 once, then side-push assembly (§V-C, eq 21)."""
    return _push("front-side-assemble", first_obs, options)


def _excitation_params(options: dict) -> tuple[ExcitationParams, dict[str, Any]]:
    """The ``identify`` options as the sweep's settings (the rest from ``models/identify.toml``), validated, and as
    logged (every option, SI, unit-suffixed keys)."""
    spec = task_options("identify")
    given = resolve_options("identify", options)
    try:
        record = ExcitationParams.resolve(**given)
    except MagctlError as err:
        raise TaskError(str(err)) from None
    return record, _logged({name: getattr(record, name) for name in spec}, spec)


@register_task("identify")
def _identify(first_obs: Observation, options: dict, params: Params) -> Task:
    """The open-loop speed sweep for identification (:mod:`magctl.control.excitation`): squares driven over a grid
    of field frequencies and rocking amplitudes, from where the robot is, away from the nearest sphere; ``done``
    after the last segment, ``failed`` on a safety stop (a sphere within ``clearance``, the field's edge within
    ``models/push.toml`` ``[common] field_margin_um``)."""
    record, logged = _excitation_params(options)
    robot = np.asarray(first_obs.robot_est, dtype=float)
    spheres = np.asarray(first_obs.spheres_est, dtype=float).reshape(-1, 2)
    w, h = field_of_view()
    if not np.all(np.isfinite(robot)) or not inside_field(robot, record.field_margin, (w, h)):
        raise TaskError(f"identify: the robot at {np.round(robot * 1e6, 1).tolist()} µm is not "
                        f"{record.field_margin * 1e6:.0f} µm inside the camera field [0, {w * 1e6:.0f}] × "
                        f"[0, {h * 1e6:.0f}] µm")
    near = np.hypot(*(spheres - robot).T) < record.clearance if len(spheres) else np.zeros(0, bool)
    if np.any(near):
        raise TaskError(f"identify: sphere(s) {np.flatnonzero(near).tolist()} within the clearance "
                        f"{record.clearance * 1e6:.0f} µm of the robot; move the robot away first")
    limits = RigLimits.from_params(params)
    for cmd in _sweep_commands(record):
        try:
            limits.check(cmd)
        except CommandRejected as err:
            raise TaskError(f"identify: the sweep's command exceeds the rig's limits: {err}") from None
    try:
        block = Excitation("task", n_spheres=len(spheres), params=record)
    except MagctlError as err:
        raise TaskError(str(err)) from None
    diagram = Diagram("controller", [block], inputs={n: f"task.{n}" for n in block.inputs},
                      outputs={n: f"task.{n}" for n in block.outputs})
    return Task("identify", diagram, logged, dict(IDENTIFY_OUTCOMES))


def _sweep_commands(record: ExcitationParams):
    """The sweep's strongest commands, at headings every 15°: the largest ``b_osc`` at the highest frequency."""
    b_osc, freq = max(record.amplitudes), max(record.frequencies)
    for th in np.radians(np.arange(0.0, 360.0, 15.0)):
        yield Command(record.static_field * np.array([np.cos(th), np.sin(th)]), b_osc, freq)
