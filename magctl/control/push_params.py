"""Parameter records of the push tasks: one frozen dataclass per ``models/push.toml`` table, and the named tuple
(:class:`TaskParams`) their kernels read them as.

A record is the one definition of a task's parameters. Its fields — name, the table and key of
``models/push.toml`` that holds the default (SI after loading), and what values are valid — give:

* the task's constructor keywords and their defaults (:meth:`PushParams.resolve`: a keyword left ``None`` takes
  the file's value);
* the validation, one line naming the task and the parameter (:meth:`PushParams.resolve`);
* the rig's option spec (:meth:`PushParams.spec`: name → (default, SI unit), the units from the file);
* the run log's round trip (:meth:`PushParams.to_log`, :meth:`PushParams.from_log`);
* the kernels' packed parameters (:meth:`PushParams.packed`: every field of :class:`TaskParams` the record has, by
  name, plus what the task derives).

The tables: ``[common]`` (:class:`CommonParams`) under ``[front]`` (:class:`FrontParams`), ``[side]``
(:class:`SideParams`), ``[assembly]`` over ``[side]`` (:class:`AssemblyParams`) and ``[plan]``
(:class:`PlannedParams`); ``[dirt]`` (:class:`DirtParams`) for the side push's answer to dirt. :func:`task_defaults`,
:func:`with_defaults` and :func:`goal_distance` read a record's defaults by its table's name.

The push tasks (:mod:`magctl.control.push`) and the assembly planners below them
(:mod:`magctl.control.assembly_planner`) read their parameters from here; this module imports nothing of
:mod:`magctl.control`.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields
from typing import Any, NamedTuple

from magctl.config import load_model
from magctl.core.errors import MagctlError

FRONT_LEARNING = {"eq13": "the paper's eq 13 law (K_c, δ(0))",
                  "release": "the controller that models its own release (magctl.control.release_model)"}
"""The front push's learning laws by name."""
SIDE_LEARNING = {"eq18": "the paper's eq 18 law correcting the fixed model F (gain K_s)",
                 "curve": "the curve D_s(D_g) re-estimated after every pass and inverted "
                          "(magctl.control.curve_learning)"}
"""The side push's learning laws by name."""
DIRT_RESPONSES = {"none": "side passes only, whatever the sphere's mobility",
                  "front": "one front push for the coarse part when the curve law reads the sphere as stuck",
                  "front-first": "a front push for the coarse move first (paper §IV-D, §V-C), then side passes "
                                 "(and front pushes for a stuck sphere as 'front', [dirt] fronts in all)"}
"""The side push's front pushes: none, for a sphere held by dirt, or first for the coarse move and then for dirt
(``learning="curve"`` for both)."""


def _from(table: str, key: str | None = None, *, check: str = "positive", choices: dict | None = None):
    """A record field whose default is ``models/push.toml`` ``[table] key`` (the field's name by default) and
    whose values must pass ``check``: ``positive``, ``nonnegative``, ``finite``, ``count`` (an integer ≥ 1),
    ``frames`` (an integer ≥ 0), ``fraction`` (in (0, 1]), ``choice`` (a key of ``choices``) or ``any``."""
    return field(metadata={"table": table, "key": key, "check": check, "choices": choices})


_CHECKS = {
    "positive": (lambda v: v > 0, "a positive number"),
    "nonnegative": (lambda v: v >= 0, "a number ≥ 0"),
    "finite": (lambda v: True, "a finite number"),
    "fraction": (lambda v: 0 < v <= 1, "a number in (0, 1]"),
    "count": (lambda v: v >= 1, "an integer ≥ 1"),
    "frames": (lambda v: v >= 0, "an integer ≥ 0"),
}


MODEL_EXP, MODEL_LIN, MODEL_TABLE = 0, 1, 2
"""``TaskParams.model``: the side push's ``F`` of eq 17 — eq 22 (``m0`` = A, ``m1`` = k), eq 23 (``m0`` = intercept,
``m1`` = slope) or the tabulated model."""
LAW_INTEGRATOR, LAW_CURVE, LAW_RELEASE = 0, 1, 2
"""``TaskParams.law``: eq 13/18 (:class:`~magctl.control.learning.LearningLaw`), the curve-learning law, the
release-model law."""


class TaskParams(NamedTuple):
    """A push task's parameters as its kernels (:mod:`magctl.control.push.kernels`) read them, by name (numba passes
    a named tuple by value).

    The names are the task's own parameters (the records below, one per ``models/push.toml`` table) where the
    kernels read one, and the values the task derives from its blocks below them; a kernel reads only the fields of
    its task, the others keep these defaults."""

    # every push task ([common], and the task's ε, attempt limit and keep-out)
    eps: float = 0.0
    clearance: float = 0.0
    arrive_tol: float = 0.0
    travel_speed: float = 0.0
    workspace: float = 0.0
    max_attempts: int = 0
    settle_frames: int = 0
    max_lost_frames: int = 0
    phase_timeout_frames: int = 0
    # which spheres: the pushed one, and for an assembly the fixed one, their radii and ε_as (eq 21)
    i0: int = 0
    i1: int = 0
    pair: bool = False
    r0: float = 0.0
    r1: float = 0.0
    eps_as: float = 0.0
    # front push ([front])
    push_tol: float = 0.0
    contact: float = 0.0
    approach: float = 0.0
    retract: float = 0.0
    push_speed: float = 0.0
    # side push ([side], [assembly] θ_n, the model of eq 17, the learning law and its dirt response)
    min_gap: float = 0.0
    d_max: float = 0.0
    behind: float = 0.0
    ahead: float = 0.0
    pass_speed: float = 0.0
    fixed: bool = False
    fixed_gap: float = 0.0
    theta_n: float = 0.0
    model: int = MODEL_EXP
    m0: float = 0.0
    m1: float = 0.0
    law: int = LAW_INTEGRATOR
    iterations: int = 0
    push_out_weight: float = 0.0
    push_out_min: float = 0.0
    dirt_mobility: float = 0.0
    dirt_passes: float = 0.0
    prior_at_min_gap: float = 0.0
    max_fronts: int = 0
    front_first: bool = False


@dataclass(frozen=True)
class PushParams:
    """Base of the records: resolution against ``models/push.toml``, validation, spec, log round trip, packing."""

    @classmethod
    def resolve(cls, what: str = "push task", **given):
        """The record with ``given`` (keywords left ``None`` take ``models/push.toml``'s value), validated;
        ``what`` names the task in errors. An unknown keyword is an error."""
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(given) - names)
        if unknown:
            raise MagctlError(f"{what}: unknown parameter(s) {', '.join(unknown)}; it takes {', '.join(sorted(names))}")
        defaults = cls.defaults()
        values = {name: defaults[name] if given.get(name) is None else given[name] for name in names}
        return cls._checked(what, values)

    @classmethod
    def defaults(cls) -> dict[str, Any]:
        """Every field's ``models/push.toml`` value (SI)."""
        push = load_model("push")
        return {f.name: _file_value(push, f) for f in fields(cls)}

    @classmethod
    def spec(cls) -> dict[str, tuple[Any, str]]:
        """Field name → (default, SI unit; ``""`` for names and counts' ``1``), for option parsers."""
        push = load_model("push")
        out = {}
        for f in fields(cls):
            table = push[f.metadata["table"]]
            out[f.name] = (_file_value(push, f), table.units[_key(f)])
        return out

    def replace(self, what: str = "push task", **changes):
        """A copy with ``changes`` (``None`` keeps the value), validated; an unknown name is an error."""
        names = {f.name for f in fields(self)}
        unknown = sorted(set(changes) - names)
        if unknown:
            raise MagctlError(f"{what}: unknown parameter(s) {', '.join(unknown)}; it takes {', '.join(sorted(names))}")
        return self._checked(what, {f.name: getattr(self, f.name) for f in fields(self)}
                             | {k: v for k, v in changes.items() if v is not None})

    def to_log(self) -> dict[str, Any]:
        """The record as JSON-able values (SI), for run logs."""
        return {k: (v if isinstance(v, (str, int, float, bool)) or v is None else repr(v))
                for k, v in asdict(self).items()}

    @classmethod
    def from_log(cls, values: dict, what: str = "push task"):
        """The record a run log wrote (:meth:`to_log`), validated."""
        return cls.resolve(what, **values)

    def packed(self, **derived):
        """The kernels' :class:`TaskParams`: this record's fields that the kernels read, by name, and ``derived``
        (values the task computes: sphere indices, the model's coefficients …)."""
        mine = {f.name: getattr(self, f.name) for f in fields(self) if f.name in TaskParams._fields}
        values = mine | derived
        unknown = sorted(set(values) - set(TaskParams._fields))
        if unknown:
            raise MagctlError(f"kernel parameters {unknown} are not fields of TaskParams")
        defaults = TaskParams._field_defaults
        return TaskParams(**{k: type(defaults[k])(v) for k, v in values.items()})

    @classmethod
    def _checked(cls, what: str, values: dict):
        for f in fields(cls):
            values[f.name] = _valid(what, f, values[f.name])
        return cls(**values)


def _key(f) -> str:
    return f.metadata["key"] or f.name


def _file_value(push, f):
    value = push[f.metadata["table"]][_key(f)]
    return int(value) if f.metadata["check"] in ("count", "frames") else value


def _valid(what: str, f, value):
    check, name = f.metadata["check"], f.name
    if check == "any":
        return value
    if check == "choice":
        choices = f.metadata["choices"]
        if value not in choices:
            raise MagctlError(f"{what}: {name}={value!r} is not one of {', '.join(choices)}")
        return value
    test, wanted = _CHECKS[check]
    given = value
    if check in ("count", "frames"):
        if isinstance(value, bool) or not _is_number(value) or not float(value).is_integer():
            raise MagctlError(f"{what}: {name}={value!r} must be {wanted}")
        value = int(value)
    elif not _is_number(value) or isinstance(value, bool):
        raise MagctlError(f"{what}: {name}={value!r} must be {wanted}")
    else:
        value = float(value)
    if not (math.isfinite(value) and test(value)):
        raise MagctlError(f"{what}: {name}={given!r} must be {wanted}")
    return value


def _is_number(value) -> bool:
    try:
        float(value)
    except (TypeError, ValueError):
        return False
    return True


@dataclass(frozen=True)
class CommonParams(PushParams):
    """``[common]``: what every push task shares (arrival tolerance, travel speed, settling, failure limits)."""

    arrive_tol: float = _from("common")
    travel_speed: float = _from("common")
    settle_frames: int = _from("common", "settle", check="frames")
    max_lost_frames: int = _from("common", "max_lost", check="frames")
    phase_timeout_frames: int = _from("common", "phase_timeout", check="count")
    workspace: float = _from("common")


@dataclass(frozen=True)
class FrontParams(CommonParams):
    """``[front]``: front pushing (§V-A, eq 10–13)."""

    kc: float = _from("front", check="finite")
    delta0: float = _from("front", check="finite")
    learning: str = _from("front", check="choice", choices=FRONT_LEARNING)
    eps: float = _from("front")
    push_tol: float = _from("front")
    max_attempts: int = _from("front", check="count")
    contact: float = _from("front")
    approach: float = _from("front")
    retract: float = _from("front")
    clearance: float = _from("common", check="nonnegative")
    push_speed: float = _from("front")


@dataclass(frozen=True)
class SideParams(CommonParams):
    """``[side]``: side pushing (§V-B, eq 16–23). ``model`` is a name of
    :data:`~magctl.control.side_models.SIDE_MODELS` or a model object."""

    ks: float = _from("side", check="finite")
    model: Any = _from("side", check="any")
    learning: str = _from("side", check="choice", choices=SIDE_LEARNING)
    push_out_weight: float = _from("side", check="fraction")
    push_out_min: float = _from("side")
    dirt_response: str = _from("side", check="choice", choices=DIRT_RESPONSES)
    eps: float = _from("side")
    max_attempts: int = _from("side", check="count")
    min_gap: float = _from("side")
    behind: float = _from("side")
    ahead: float = _from("side")
    clearance: float = _from("side", check="nonnegative")
    pass_speed: float = _from("side")


@dataclass(frozen=True)
class AssemblyParams(SideParams):
    """``[assembly]`` over ``[side]``: two-sphere assembly by side pushing (§V-C, eq 21), ``K_s`` its own."""

    ks: float = _from("assembly", check="finite")
    theta_n: float = _from("assembly", check="nonnegative")
    eps_as: float = _from("assembly", check="nonnegative")


@dataclass(frozen=True)
class PlannedParams(CommonParams):
    """``[plan]`` with ``[side]``'s pushing speed and ``[assembly]``'s ``ε_as``: assembly by planned passes
    (docs/push-control.md §8); its attempt limit is ``max_passes`` and its keep-out the repositioning clearance."""

    max_attempts: int = _from("plan", "max_passes", check="count")
    clearance: float = _from("common", check="nonnegative")
    pass_speed: float = _from("side")
    eps_as: float = _from("assembly", check="nonnegative")


@dataclass(frozen=True)
class DirtParams(PushParams):
    """``[dirt]``: when and how the side push answers a sphere held by dirt with front pushes."""

    mobility: float = _from("dirt", check="fraction")
    passes: float = _from("dirt")
    push_tol: float = _from("dirt")
    fronts: int = _from("dirt", check="count")


RECORDS = {"common": CommonParams, "front": FrontParams, "side": SideParams, "assembly": AssemblyParams,
           "plan": PlannedParams, "dirt": DirtParams}
"""The records by the ``models/push.toml`` table they are named after."""


def task_parameters(table: str) -> dict[str, tuple[Any, str]]:
    """The parameters of the record named after ``models/push.toml`` table ``table`` (``"front"``, ``"side"``,
    ``"assembly"``, ``"plan"``, ``"common"``) as keyword → (SI default, SI unit)."""
    return RECORDS[table].spec()


def task_defaults(table: str) -> dict:
    """Keyword defaults (SI) of a push task (see :func:`task_parameters`)."""
    return RECORDS[table].defaults()


def with_defaults(table: str, **given) -> dict:
    """``given`` with every None replaced by its :func:`task_defaults` value."""
    defaults = task_defaults(table)
    return {k: defaults[k] if v is None else v for k, v in given.items()}


def goal_distance(table: str) -> float:
    """Default goal distance of a task (m): how far beyond the sphere, away from the robot (§VI)."""
    return float(load_model("push")[table].goal_distance)

__all__ = ["AssemblyParams", "CommonParams", "DIRT_RESPONSES", "DirtParams", "FRONT_LEARNING", "FrontParams",
           "LAW_CURVE", "LAW_INTEGRATOR", "LAW_RELEASE", "MODEL_EXP", "MODEL_LIN", "MODEL_TABLE", "PlannedParams",
           "PushParams", "RECORDS", "SIDE_LEARNING", "SideParams", "TaskParams", "goal_distance", "task_defaults",
           "task_parameters", "with_defaults"]
