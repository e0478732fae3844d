"""What the page draws, from a run's own documents: the scene's fixed part and the error of each attempt.

The fixed part comes from the start document alone — the camera field from the run's own ``camera.toml``, the
robot's outline from its ``robot_geometry.toml`` and the sphere radius from its ``sphere.toml`` (the texts in
``models_toml``, so a log drawn years later is drawn with the geometry it ran with), the goal, its ε band and the
contact threshold from the resolved task options, the coil ratings from the logged limits — so the live page and
the replay page of one run draw the same picture.

The error per attempt is the distance from the goal to the nearest sphere at the frame where the task's
``attempt`` output steps (the end of that attempt), the quantity the push laws (eq 13-20) drive below ε. The
passes are the lines the robot pushed along: each begins where the robot was when the task entered its pushing
phase (the side push's ``pass``, the front push's ``push``) and ends at the servo's target of that phase — the
motion line's end (§VI).
"""

from __future__ import annotations

import math
import tomllib
from typing import Any

from magctl.config import Params, models_dir, parse_params
from magctl.control.status import STATUS_NAMES
from magctl.core.errors import ParameterError
from magctl.plant.outline import RobotOutline
from magctl.rig.log import task_phases

_CAMERA_KEYS = {"camera": ("width_px", "height_px", "pixel_size_um")}


def _camera_table(models_toml: dict[str, str] | None) -> dict[str, float]:
    """The field values of the run's camera.toml (the shipped file when the log carries none)."""
    text = (models_toml or {}).get("camera.toml")
    if not isinstance(text, str):
        text = (models_dir() / "camera.toml").read_text("utf-8")
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ValueError(f"camera.toml: {err}") from None
    out = {}
    for table, keys in _CAMERA_KEYS.items():
        for key in keys:
            entry = (doc.get(table) or {}).get(key)
            value = entry.get("value") if isinstance(entry, dict) else entry
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
                    or value <= 0:
                raise ValueError(f"camera.toml: [{table}] {key} is missing or not a positive number")
            out[key] = float(value)
    return out


def _logged_params(models_toml: dict[str, str] | None, name: str) -> Params:
    """The run's own parameter file ``name`` (the shipped one when the log carries none)."""
    text = (models_toml or {}).get(name)
    if not isinstance(text, str):
        text = (models_dir() / name).read_text("utf-8")
    try:
        return parse_params(text, name)
    except ParameterError as err:
        raise ValueError(str(err)) from None


def _shapes(models_toml: dict[str, str] | None) -> dict[str, Any]:
    """The robot's outline (body frame, m, counter-clockwise) and the sphere radius the run was simulated or tracked
    with."""
    try:
        robot = RobotOutline.from_params(_logged_params(models_toml, "robot_geometry.toml"))
        radius = float(_logged_params(models_toml, "sphere.toml").sphere.radius)
    except (ParameterError, AttributeError) as err:
        raise ValueError(f"the run's robot or sphere geometry: {err}") from None
    if not (math.isfinite(radius) and radius > 0):
        raise ValueError(f"sphere.toml: [sphere] radius {radius!r} is not a positive number")
    return {"robot": {"length_m": robot.length, "width_m": robot.width,
                      "outline_m": [[float(x), float(y)] for x, y in robot.vertices]},
            "sphere_radius_m": radius}


def _finite(x) -> float | None:
    return float(x) if isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) else None


def _point(x) -> list[float] | None:
    if isinstance(x, (list, tuple)) and len(x) == 2 and all(_finite(v) is not None for v in x):
        return [float(x[0]), float(x[1])]
    return None


def scene_of(start: dict[str, Any], n_spheres: int | None = None) -> dict[str, Any]:
    """The scene's fixed part (SI units), JSON-able, from a run's start document."""
    cam = _camera_table(start.get("models_toml"))
    pixel = cam["pixel_size_um"] * 1e-6
    options = start.get("options") or {}
    task = start.get("task")
    contact, contact_label = None, None
    if _finite(options.get("min_gap_m")) is not None:
        contact, contact_label = float(options["min_gap_m"]), "side push: closest pass (min_gap)"
    elif _finite(options.get("contact_m")) is not None:
        contact, contact_label = float(options["contact_m"]), "front push: contact distance"
    limits = start.get("limits") or {}
    n = n_spheres if n_spheres is not None else int((start.get("rig") or {}).get("n_spheres", 1) or 0)
    return {
        "uid": start.get("uid"), "task": task, "seed": start.get("seed"), "period_s": start.get("period_s"),
        # pixel centres span [0, (W−1)·s] (magctl.sensing.camera.view_span)
        "field_m": [(cam["width_px"] - 1) * pixel, (cam["height_px"] - 1) * pixel], "pixel_m": pixel,
        **_shapes(start.get("models_toml")), "n_spheres": n,
        "goal_m": _point(options.get("goal_m")), "target_m": _point(options.get("target_m")),
        "eps_m": _finite(options.get("eps_m")), "contact_m": contact, "contact_label": contact_label,
        "coil_names": list(limits.get("coil_names") or []),
        "coil_limit_A": [float(x) for x in limits.get("coil_current_limit_A") or []],
        "b_static_max_T": _finite(limits.get("b_static_max_T")), "b_osc_max_T": _finite(limits.get("b_osc_max_T")),
        "freq_max_Hz": _finite(limits.get("freq_max_Hz")),
        "phases": {str(k): v for k, v in task_phases(task).items()},
        "statuses": {str(k): v for k, v in STATUS_NAMES.items()},
        "max_attempts": _finite(options.get("max_attempts")),
    }


class AttemptErrors:
    """The goal distance at the end of each attempt, fed event by event (O(1) a frame)."""

    def __init__(self, goal_m: list[float] | None):
        self.goal = goal_m
        self.rows: list[dict[str, float]] = []
        self._attempt: float | None = None

    def update(self, event: dict[str, Any]) -> dict[str, float] | None:
        """Take one event document; returns the new row when this frame ends an attempt."""
        if self.goal is None or event.get("paused"):
            return None
        attempt = event.get("outputs", {}).get("attempt")
        if not isinstance(attempt, (int, float)) or isinstance(attempt, bool):
            return None
        previous, self._attempt = self._attempt, float(attempt)
        if previous is None or attempt <= previous:
            return None
        spheres = event["obs"]["spheres_est_m"]
        if not spheres:
            return None
        gx, gy = self.goal
        error = min(math.hypot(s[0] - gx, s[1] - gy) for s in spheres)
        row = {"attempt": int(attempt), "seq": int(event["seq"]), "t_s": float(event["obs"]["t_s"]),
               "error_m": error}
        self.rows.append(row)
        return row


PUSHING_PHASES = ("pass", "push")
"""The last word of the phase names in which a push task drives the robot along its motion line."""


class Passes:
    """The motion lines of the passes so far, fed event by event (O(1) a frame)."""

    def __init__(self, phases: dict[str, str]):
        self.codes = {int(k) for k, name in phases.items() if name.split()[-1] in PUSHING_PHASES}
        self.rows: list[dict[str, Any]] = []
        self._pushing = False

    def update(self, event: dict[str, Any]) -> dict[str, Any] | None:
        """Take one event document; returns the new pass when the task enters a pushing phase at this frame."""
        if event.get("paused"):
            return None
        outputs = event.get("outputs", {})
        phase = outputs.get("phase")
        pushing = isinstance(phase, (int, float)) and not isinstance(phase, bool) and int(phase) in self.codes
        entered, self._pushing = pushing and not self._pushing, pushing
        end = _point(outputs.get("target"))
        if not entered or end is None:
            return None
        attempt = outputs.get("attempt")
        row = {"seq": int(event["seq"]), "attempt": int(attempt) + 1 if isinstance(attempt, (int, float)) else None,
               "start_m": list(event["obs"]["robot_est_m"]), "end_m": end}
        self.rows.append(row)
        return row
