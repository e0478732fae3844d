"""From camera frames to observations: the pixel calibration and the frame tracker.

**Pixel calibration** (:class:`PixelCalibration`). Image pixel (column ``j``, row ``i``) → glass coordinates, m::

    glass = origin + R(rotation) · diag(1, ±1) · s · (j, i)

with ``s`` the pixel size (m/px) and the minus sign when the image is mirrored relative to the coil axes
(``mirror``). Headings map as ``θ_glass = rotation ± θ_image``. The identity calibration
(:meth:`PixelCalibration.identity`) is ``models/camera.toml``'s 7.5 µm pixel, unrotated, unmirrored, origin 0:
then glass coordinates are the renderer's (:func:`magctl.sensing.camera.render_frame`: pixel ``(i, j)`` centred
at ``(j·s, i·s)``), so the simulator and a camera in front of it agree. In a parameter table the keys carry their
units as everywhere in magctl (:mod:`magctl.config`): ``pixel_size_um``, ``rotation_deg``, ``mirror`` (a boolean:
no unit), ``origin_x_um``, ``origin_y_um``.

**Frame tracker** (:class:`FrameTracker`). Each :class:`~magctl.rig.devices.base.Frame` becomes one
:class:`~magctl.rig.interface.Observation` through the particle-filter tracker of the simulator
(:class:`magctl.sensing.particle_filter.ImageTracker`, parameters from ``models/camera.toml``), in glass
coordinates through the calibration:

* dropped frames — gaps in the device's frame numbers — are counted (:attr:`FrameTracker.dropped`) and given to
  the tracker as invalid frames, one per missing frame (at most :data:`MAX_GAP_STEPS`), so its motion model
  keeps time; a number that does not increase counts no drop;
* brightness is normalised before tracking: each frame is scaled so that its median (the background: the robot
  and the spheres cover a few percent of the field) equals the render background level of
  ``models/camera.toml``. In bright field the objects' levels are the illumination times their transmittance, so
  one factor undoes a lighting change for the whole frame and the tracker's levels and edge contrasts hold;
* a blank frame (after normalisation, fewer dark pixels than a quarter of the smallest object: a camera that
  delivered only background, a dark or saturated frame) and a damaged one (pixels not finite, or a shape other
  than the camera's) are lost frames: the tracker steps them as invalid frames and the observation is
  ``lost``;
* ``lost`` is also set on every frame where the tracker does not find the robot and every sphere, and before
  the first detection. The estimates of a lost observation are the tracker's prediction (finite: observations
  travel as JSON); consumers gate on ``lost``.

Coil currents are left to the caller (zeros).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from magctl import FRAME_PERIOD_S
from magctl.config import UNITS, Params, read_toml, split_unit
from magctl.core.errors import ParameterError
from magctl.rig.devices.base import Frame, dropped_between
from magctl.rig.interface import Observation
from magctl.sensing.camera import camera_params
from magctl.sensing.particle_filter import DetectionError, ImageTracker

MAX_GAP_STEPS = 300
"""At most this many invalid frames are stepped for one gap in the frame numbers (10 s at 30 frames/s: beyond
that the motion model predicts nothing, and a device whose numbers jump by millions must not stall the tracker)."""

# calibration name → (SI unit of its value, the unit it is written in by to_params)
_KEYS = {"pixel_size": ("m", "um"), "rotation": ("rad", "deg"), "mirror": (None, None),
         "origin_x": ("m", "um"), "origin_y": ("m", "um")}


def _wrap(angle: float) -> float:
    return float(math.atan2(math.sin(angle), math.cos(angle)))


@dataclass(frozen=True)
class PixelCalibration:
    """Image pixels (column ``j``, row ``i``) → glass coordinates (m), see the module docstring.

    Attributes
    ----------
    pixel_size : float
        m per pixel, > 0.
    rotation : float
        rad: the direction of the image's column axis (+j) in glass coordinates.
    mirror : bool
        The image is mirrored: the row axis (+i) is the column axis turned by −90° instead of +90°.
    origin : (2,) tuple
        Glass coordinates of pixel (0, 0), m.
    """

    pixel_size: float
    rotation: float = 0.0
    mirror: bool = False
    origin: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self):
        s, rot = float(self.pixel_size), float(self.rotation)
        origin = tuple(float(v) for v in np.asarray(self.origin, dtype=float).reshape(2))
        if not (math.isfinite(s) and s > 0):
            raise ParameterError(f"pixel calibration: pixel size must be > 0 m, got {self.pixel_size!r}")
        if not (math.isfinite(rot) and all(math.isfinite(v) for v in origin)):
            raise ParameterError(f"pixel calibration: rotation {self.rotation!r} and origin {self.origin!r} "
                                 "must be finite")
        object.__setattr__(self, "pixel_size", s)
        object.__setattr__(self, "rotation", rot)
        object.__setattr__(self, "mirror", bool(self.mirror))
        object.__setattr__(self, "origin", origin)

    # --- construction ----------------------------------------------------------------------------------------
    @classmethod
    def identity(cls, params: Params | None = None) -> PixelCalibration:
        """``models/camera.toml``'s pixel size, no rotation, no mirror, origin 0 (glass = renderer coordinates)."""
        cam = (params if params is not None else camera_params()).camera
        return cls(float(cam.pixel_size))

    @classmethod
    def from_params(cls, table: Mapping | Params, default: PixelCalibration | None = None) -> PixelCalibration:
        """A calibration from a parameter table: ``pixel_size_um``, ``rotation_deg``, ``mirror``, ``origin_x_um``,
        ``origin_y_um`` (any unit suffix of the right kind, e.g. ``rotation_rad``), each a plain value or a
        ``{ value, source }`` entry, or a parsed :class:`~magctl.config.Params` table.

        Missing keys keep ``default``'s values (the identity calibration by default). Other keys are ignored (the
        table may hold a camera's other settings) unless they begin with a calibration name — a misspelt
        ``mirror_bool`` or a ``pixel_size_px`` is a :class:`ParameterError` naming the key.
        """
        raw = table.raw if isinstance(table, Params) else table
        base = default if default is not None else cls.identity()
        values: dict[str, object] = {"pixel_size": base.pixel_size, "rotation": base.rotation,
                                     "mirror": base.mirror, "origin_x": base.origin[0], "origin_y": base.origin[1]}
        for key, entry in raw.items():
            value = entry["value"] if isinstance(entry, Mapping) and "value" in entry else entry
            name, suffix = split_unit(key)
            if name not in _KEYS:
                if any(key.startswith(k) for k in _KEYS):
                    raise ParameterError(f"pixel calibration: unknown key {key!r} (keys: pixel_size_um, "
                                         "rotation_deg, mirror, origin_x_um, origin_y_um)")
                continue
            si = _KEYS[name][0]
            if si is None:  # mirror
                if suffix is not None or not isinstance(value, bool):
                    raise ParameterError(f"pixel calibration: {key} must be written 'mirror = true' or "
                                         f"'mirror = false', got {key} = {value!r}")
                values[name] = value
                continue
            if suffix is None or UNITS[suffix][0] != si:
                raise ParameterError(f"pixel calibration: {key} needs a unit suffix in {si} "
                                     f"(e.g. {name}_{_KEYS[name][1]})")
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ParameterError(f"pixel calibration: {key} = {value!r} is not a number")
            values[name] = float(value) * UNITS[suffix][1]
        return cls(values["pixel_size"], values["rotation"], values["mirror"],
                   (values["origin_x"], values["origin_y"]))

    def to_params(self) -> dict[str, float | bool]:
        """The calibration as a table of plain values in the units of :meth:`from_params`
        (``from_params(c.to_params()) == c`` to rounding)."""
        return {"pixel_size_um": float(f"{self.pixel_size / 1e-6:.12g}"),
                "rotation_deg": float(f"{math.degrees(self.rotation):.12g}"), "mirror": self.mirror,
                "origin_x_um": float(f"{self.origin[0] / 1e-6:.12g}"),
                "origin_y_um": float(f"{self.origin[1] / 1e-6:.12g}")}

    @classmethod
    def load(cls, path: str | os.PathLike) -> PixelCalibration:
        """A calibration file: a ``[calibration]`` table (or top-level keys) as :meth:`from_params` reads them."""
        path = Path(path)
        data = read_toml(path, "calibration file")
        table = data.get("calibration", data)
        if not isinstance(table, Mapping):
            raise ParameterError(f"{path}: [calibration] must be a table")
        try:
            return cls.from_params(table)
        except ParameterError as err:
            raise ParameterError(f"{path}: {err}") from None

    def save(self, path: str | os.PathLike, source: str = "measured: magctl pixel calibration") -> None:
        """Write a ``[calibration]`` table in magctl's parameter format (``{ value, source }`` entries), readable by
        :meth:`load` and by :func:`magctl.config.load_file`."""
        lines = ["[calibration]"]
        for key, value in self.to_params().items():
            text = ("true" if value else "false") if isinstance(value, bool) else repr(float(value))
            lines.append(f"{key} = {{ value = {text}, source = {json.dumps(source)} }}")
        Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")

    # --- the transform ---------------------------------------------------------------------------------------
    @property
    def matrix(self) -> np.ndarray:
        """The 2 × 2 linear part ``s · R(rotation) · diag(1, ±1)``: m per pixel."""
        c, sn = math.cos(self.rotation), math.sin(self.rotation)
        flip = -1.0 if self.mirror else 1.0
        return self.pixel_size * np.array([[c, -sn * flip], [sn, c * flip]])

    def to_glass(self, pixels) -> np.ndarray:
        """Pixel coordinates ``(..., 2)`` as (column j, row i) → glass coordinates ``(..., 2)``, m."""
        p = np.asarray(pixels, dtype=float)
        return np.asarray(self.origin) + p @ self.matrix.T

    def to_pixels(self, glass) -> np.ndarray:
        """Glass coordinates ``(..., 2)``, m → pixel coordinates ``(..., 2)`` as (column j, row i)."""
        g = np.asarray(glass, dtype=float) - np.asarray(self.origin)
        return g @ np.linalg.inv(self.matrix).T

    def heading_to_glass(self, theta_image: float) -> float:
        """An image heading (rad, from +j towards +i) → glass heading, wrapped to (−π, π]."""
        return _wrap(self.rotation + (-theta_image if self.mirror else theta_image))

    def heading_to_image(self, theta_glass: float) -> float:
        """A glass heading → image heading (the inverse of :meth:`heading_to_glass`)."""
        d = theta_glass - self.rotation
        return _wrap(-d if self.mirror else d)


class FrameTracker:
    """Frames → observations in glass coordinates (see the module docstring for the rules).

    Parameters
    ----------
    n_spheres : int
    calibration : PixelCalibration, optional
        Pixels → glass; the identity calibration by default. Its pixel size sets the objects' sizes in pixels.
    dt : float
        The camera's nominal frame period, s (the tracker's motion model steps by it).
    params : Params, optional
        ``models/camera.toml`` (tables ``render`` and ``tracker``).
    init_robot, init_heading, init_spheres : optional
        Where the robot (m), its heading (rad) and the spheres ((N, 2) m) start, in glass coordinates; without
        them the tracker detects the objects on the first frame that shows them.
    shape : (height, width), optional
        The frames' shape (the camera's); by default that of the first usable frame.
    seed : int
        Seed of the particle filters.
    normalise : bool
        Scale each frame's background to the render background level (see the module docstring).
    """

    def __init__(self, n_spheres: int, *, calibration: PixelCalibration | None = None, dt: float = FRAME_PERIOD_S,
                 params: Params | None = None, init_robot=None, init_heading: float = 0.0, init_spheres=None,
                 shape: tuple[int, int] | None = None, seed: int = 0, normalise: bool = True):
        self.params = params if params is not None else camera_params()
        self.calibration = calibration if calibration is not None else PixelCalibration.identity(self.params)
        self.n_spheres = int(n_spheres)
        self.dt = float(dt)
        self.normalise = bool(normalise)
        self.shape = None if shape is None else (int(shape[0]), int(shape[1]))
        cal, s = self.calibration, self.calibration.pixel_size
        init = {}
        if init_robot is not None:
            robot_px = cal.to_pixels(np.asarray(init_robot, dtype=float).reshape(2))
            sph = np.zeros((0, 2)) if init_spheres is None else np.asarray(init_spheres, dtype=float).reshape(-1, 2)
            init = {"init_robot": robot_px * s, "init_heading": cal.heading_to_image(float(init_heading)),
                    "init_spheres": cal.to_pixels(sph) * s}
        self.tracker = ImageTracker(self.params, n_spheres=self.n_spheres, pixel=s, dt=self.dt, seed=seed, **init)
        r = self.params.render
        self.background = float(r.background)
        self.dark_level = float(r.background - 0.5 * (r.background - r.sphere_level))
        shapes = self.tracker.shapes
        robot_area = shapes.robot.area / s**2
        sphere_area = math.pi * (shapes.sphere_radius / s) ** 2 if self.n_spheres else robot_area
        self.min_dark_pixels = max(4, int(0.25 * min(robot_area, sphere_area)))
        self.last_number: int | None = None
        self.dropped = 0
        """Frames missing from the device's numbers."""
        self.frames = 0
        """Frames tracked (delivered ones)."""
        self.blanks = 0
        """Delivered frames that showed nothing (blank, dark or saturated)."""
        self.damaged = 0
        """Delivered frames with pixels that are not finite or the wrong shape."""
        self.lost_frames = 0
        """Delivered frames whose observation is lost."""
        self._estimate = self._from_tracker(*self._tracker_estimate())
        self._t = 0.0

    # --- observations ----------------------------------------------------------------------------------------
    def _tracker_estimate(self):
        trk, s = self.tracker, self.tracker.pixel
        robot = trk.robot.estimate[:2] * s
        sph = np.array([f.estimate[:2] * s for f in trk.spheres]).reshape(-1, 2)
        return robot, float(trk.robot.estimate[2]), sph

    def _from_tracker(self, robot_m, heading, spheres_m):
        """The tracker's renderer coordinates (m, pixel (i, j) at (j·s, i·s)) → glass coordinates."""
        s, cal = self.tracker.pixel, self.calibration
        robot = cal.to_glass(np.asarray(robot_m, dtype=float) / s)
        spheres = cal.to_glass(np.asarray(spheres_m, dtype=float).reshape(-1, 2) / s).reshape(-1, 2)
        return robot, cal.heading_to_glass(float(heading)), spheres

    def blank(self, t: float, frame: int) -> Observation:
        """A lost observation stamped ``t`` and ``frame`` with the current estimates (before any frame: the
        initial positions, or pixel (0, 0) when none were given)."""
        robot, heading, spheres = self._estimate
        return Observation(t=float(t), frame=int(frame), robot_est=robot.copy(), heading_est=heading,
                           spheres_est=spheres.copy(), lost=True)

    def lost_frame(self) -> Observation:
        """The camera delivered no frame: the last estimates, lost (the tracker is not stepped: the next frame's
        number shows how many were missed)."""
        return self.blank(self._t, self.last_number if self.last_number is not None else 0)

    def track(self, frame: Frame) -> Observation:
        """Track one frame (dropped frames before it from the numbers); its observation in glass coordinates."""
        number = int(frame.number)
        missing = dropped_between(self.last_number, number)
        self.dropped += missing
        self.last_number = number
        self._t = float(frame.t)
        self.frames += 1
        for _ in range(min(missing, MAX_GAP_STEPS)):
            self.tracker.step(None, False)
        image, usable = self._prepare(frame.image)
        try:
            robot, heading, _, spheres, found = self.tracker.step(image, usable)
        except DetectionError:  # not started, and the objects are not all in view yet: the next frame may show them
            robot, heading, spheres = self._tracker_estimate()
            found = False
        lost = not (usable and found and self.tracker.started)
        self.lost_frames += lost
        self._estimate = self._from_tracker(robot, heading, spheres)
        return self.blank(frame.t, number) if lost else Observation(
            t=float(frame.t), frame=number, robot_est=self._estimate[0].copy(), heading_est=self._estimate[1],
            spheres_est=self._estimate[2].copy(), lost=False)

    def _prepare(self, image) -> tuple[np.ndarray | None, bool]:
        """The frame normalised for the tracker and whether it is usable (finite, right shape, not blank)."""
        img = np.asarray(image)
        if img.ndim != 2 or img.dtype.kind not in "fiu":
            self.damaged += 1
            return None, False
        if (self.shape is not None and img.shape != self.shape) or not np.all(np.isfinite(img)):
            self.damaged += 1
            return None, False
        img = img.astype(float, copy=False)
        if self.normalise:
            # a strided sample is enough for the median and 16× cheaper on a VGA frame
            level = float(np.median(img[::4, ::4]))
            if level <= 0.02:  # dark frame: nothing to scale
                self.blanks += 1
                return None, False
            img = img * (self.background / level)
        if np.count_nonzero(img < self.dark_level) < self.min_dark_pixels:
            self.blanks += 1
            return None, False
        if self.shape is None:  # the first frame that shows something sets the shape
            self.shape = img.shape
        return img, True
