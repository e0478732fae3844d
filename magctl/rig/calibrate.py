"""Calibrating a lab rig with its own camera and coils (``magctl rig calibrate camera`` / ``calibrate coils``).

Both calibrations drive the rig through its :class:`~magctl.rig.station.DeviceStation` — coil outputs written to
its coil driver every frame (the board's deadline needs them), frames taken from its camera — and measure the
frames themselves; the station's tracker is not used for the measurements. The coils carry static currents only
(no oscillation, ``b_osc = 0``): the robot turns in place and does not walk.

**Camera** (:func:`calibrate_camera`): the pixel calibration of :mod:`magctl.rig.devices.tracking`
(``glass = origin + s · R(rotation) · diag(1, ±1) · (j, i)``).

* *Pixel size* ``s`` from a target of known diameter ``D`` (the spheres, ``models/sphere.toml``; or a
  calibration disc, ``target_diameter``): every round dark blob of about the target's size in pixels (a factor
  of two either way at the lab's current pixel size) is fitted with a blurred disc — the intensity of the pixels
  near its edge ``b − C·Φ((R − r)/σ)``, centre, radius, blur, background and contrast free — and the radius is
  corrected for the blur's curvature bias (a blurred disc crosses its mid level at ``R − σ²/2R``). ``s = D / 2R̄``
  averaged over frames and spheres; its standard error from the scatter of the per-sphere means (one sphere: of
  the frames). The target's own size tolerance is not in it: the calibration is relative to the nominal ``D``.
* *Rotation and mirror* from the robot's heading: the static field is commanded in several directions
  ``φ_k`` (``setpoint_of`` of the lab's coil map); after :data:`SETTLE_TAUS` heading time constants
  (:func:`magctl.plant.robot.heading_time_constant`) the robot points along the field, and its heading in the
  image ``θ_k`` is measured from its blob — the principal axis of the darkness, the sign from the notch (the
  centroid lies behind the middle of the blob's extent, the notch takes material from the front). The glass
  heading is ``rotation ± θ_k``; both signs are fitted by least squares (the circular mean of ``φ_k ∓ θ_k``) and
  the one with the smaller residual is the mirror. The robot's magnetisation is taken to lie along its body axis
  towards the notch: an offset of it reads as a camera rotation.
* *Origin*: not observable from field directions; the image centre is kept at the glass point the lab's current
  calibration puts it (``centre``, µm, to set it).

**Coils** (:func:`calibrate_coils`): each in-plane coil's field at the workspace centre per ampere, as a gain
and a rotation of its column of the actuation matrix ``A`` (``models/coils.toml``,
:meth:`magctl.plant._coilfield.CoilSet.actuation_matrix`). Single in-plane coils and neighbouring pairs are
driven with known currents around the circle in steps of at most ``max_step_deg`` (16 settings for four coils), the
settled heading read through the lab's camera calibration; the field of setting ``j`` is
``Σ_k g_k n_k (cos β_k, sin β_k) i_jk`` (``n_k`` the model's in-plane field per ampere) and the directions
``β_k`` and the gains ``g_k`` are fitted to the headings by least squares (:func:`scipy.optimize.least_squares`,
standard errors from the Jacobian and the residuals). A heading does not depend on the field's magnitude, so the
common scale of the gains is not observable: the in-plane gains' geometric mean is held at 1 (the model's
scale) unless a Hall-probe reading of some coil's field per ampere is given (``hall_mT_per_A``). The vertical
coils (zp, zn) make no in-plane field at the centre, so the heading does not respond to them: they keep the
model's column and are reported as not calibrated.

Both write TOML parameter files in the style of ``models/*.toml`` (``key = { value = …, source = "…" }``): the
camera's a ``[calibration]`` table that :meth:`~magctl.rig.devices.tracking.PixelCalibration.load` reads (lab.toml
``[tracker] calibration``), the coils' a ``[coil.<name>]`` table per coil with ``gain_ratio`` and ``angle_deg``
that :func:`load_coil_calibration` reads (lab.toml ``[coils] calibration``: :func:`adjusted_coil_map`).
"""

from __future__ import annotations

import json
import math
import queue
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import ndimage, optimize, special

from magctl.config import read_toml
from magctl.core.errors import MagctlError
from magctl.plant.outline import RobotOutline
from magctl.sensing.camera import principal_axis, robot_sdf, seen_shapes

SETTLE_TAUS = 12.0
"""Heading time constants to wait after a field step: a 120° step settles to 1e-5 rad (tan(e/2) ∝ e^{−t/τ})."""
MAX_STEP_DEG = 60.0
"""Largest change of the field's direction between two settings (a 180° step would start the robot at its
unstable equilibrium)."""
SETTLE_TOLERANCE_DEG = 0.5
"""A heading that changes more than this over a setting's measured frames is still turning: an error."""
MIN_TARGET_PX = 8.0
"""Smallest target diameter in pixels the disc fit accepts (its edge and interior must be resolved)."""


class CalibrationError(MagctlError):
    """A calibration cannot be made (nothing to measure, the robot not found, a fit that does not hold)."""


def _wrap(a):
    return np.arctan2(np.sin(a), np.cos(a))


def _circmean(a) -> float:
    a = np.asarray(a, dtype=float)
    return float(np.arctan2(np.sin(a).mean(), np.cos(a).mean()))


def _toml_str(text: str) -> str:
    return json.dumps(text, ensure_ascii=False)  # a JSON string is a TOML basic string


# --- image measurements ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Blob:
    """A connected dark region of a frame.

    Attributes
    ----------
    label : int
        Its label in the frame's label image.
    area : int
        Pixels below the threshold.
    centre : (2,) ndarray
        Centroid (column j, row i), px.
    elongation : float
        √(λ₁/λ₂) of its second moments (1 for a disc, about 1.5 for the 310 × 480 µm robot).
    box : tuple of slices
        Bounding box (rows, columns).
    border : bool
        It touches the frame's edge.
    """

    label: int
    area: int
    centre: np.ndarray
    elongation: float
    box: tuple
    border: bool


@dataclass
class Segmentation:
    """A frame split into background and dark blobs (threshold ``background − max(6σ, 0.1·background)`` with
    ``σ`` the noise from the median absolute deviation)."""

    image: np.ndarray
    background: float
    noise: float
    labels: np.ndarray
    blobs: list[Blob]


def segment(image, min_area: int = 12) -> Segmentation:
    """The dark blobs of a grayscale frame (objects darker than a bright-field background)."""
    img = np.asarray(image, dtype=float)
    if img.ndim != 2 or not np.all(np.isfinite(img)):
        raise CalibrationError("frame is not a finite grayscale image")
    sample = img[::2, ::2]
    bg = float(np.median(sample))
    noise = 1.4826 * float(np.median(np.abs(sample - bg)))
    labels, _ = ndimage.label(img < bg - max(6.0 * noise, 0.1 * bg))
    h, w = img.shape
    blobs = []
    for k, box in enumerate(ndimage.find_objects(labels), start=1):
        if box is None:
            continue
        ii, jj = np.nonzero(labels[box] == k)
        if ii.size < min_area:
            continue
        jj = jj + box[1].start
        ii = ii + box[0].start
        cov = np.cov(np.vstack([jj, ii]).astype(float))
        lam = np.linalg.eigvalsh(cov)
        elong = math.sqrt(lam[1] / max(lam[0], 1e-12))
        border = box[0].start == 0 or box[1].start == 0 or box[0].stop == h or box[1].stop == w
        blobs.append(Blob(k, int(ii.size), np.array([jj.mean(), ii.mean()]), elong, box, border))
    return Segmentation(img, bg, noise, labels, blobs)


def disc_diameter(seg: Segmentation, blob: Blob) -> float | None:
    """The diameter (px) of a dark disc, fitted to its edge; None when it cannot be measured here (too close to
    the frame's edge or to another blob, too small, or the fit fails).

    The pixels within ±(4 px + 2σ_guess) of the blob's equivalent radius are fitted with
    ``b − C·Φ((R − r)/σ)`` (``r`` the distance to a free centre); the returned ``2(R + σ²/2R)`` undoes the
    blurred disc's curvature bias.
    """
    img, r0 = seg.image, math.sqrt(blob.area / math.pi)
    if 2 * r0 < MIN_TARGET_PX:
        return None
    half = 6.0
    reach = r0 + half + 3.0
    cj, ci = blob.centre
    h, w = img.shape
    i0, i1 = int(math.floor(ci - reach)), int(math.ceil(ci + reach)) + 1
    j0, j1 = int(math.floor(cj - reach)), int(math.ceil(cj + reach)) + 1
    if i0 < 0 or j0 < 0 or i1 > h or j1 > w:
        return None
    win = img[i0:i1, j0:j1]
    lab = seg.labels[i0:i1, j0:j1]
    yy, xx = np.mgrid[i0:i1, j0:j1].astype(float)
    rr = np.hypot(xx - cj, yy - ci)
    if np.any((lab != 0) & (lab != blob.label) & (rr <= reach)):
        return None  # another object's edge would enter the fit
    sel = np.abs(rr - r0) <= half
    x, y, v = xx[sel], yy[sel], win[sel]
    outer = v[rr[sel] > r0 + half - 2.0]
    inner = v[rr[sel] < r0 - half + 2.0]
    b0 = float(np.median(outer))
    c0 = b0 - float(np.median(inner))
    if c0 < 5.0 * max(seg.noise, 1e-3):
        return None

    def resid(p):
        jc, ic, radius, sigma, b, c = p
        r = np.hypot(x - jc, y - ic)
        return b - c * 0.5 * special.erfc((r - radius) / (math.sqrt(2.0) * abs(sigma))) - v

    fit = optimize.least_squares(resid, [cj, ci, r0, 1.0, b0, c0], x_scale=[0.3, 0.3, 0.3, 0.3, 0.05, 0.05])
    jc, ic, radius, sigma, _, c = fit.x
    if not fit.success or c <= 0 or radius <= 0 or abs(radius - r0) > 3.0 or abs(sigma) > half / 2:
        return None
    return 2.0 * (radius + sigma**2 / (2.0 * radius))


@dataclass(frozen=True)
class RobotPose:
    """The robot's blob in a frame: its reference point (column j, row i) px, its heading in the image (rad, from +j
    towards +i) and ``margin``, the pixels by which the outline at this heading covers the blob better than turned
    by half a turn (how sure the front is the front)."""

    centre: np.ndarray
    heading: float
    margin: float


def robot_pose(seg: Segmentation, robot_area_px: float, outline_px: RobotOutline | None = None) -> RobotPose | None:
    """The robot's pose in the image, or None when no blob looks like it (elongated, not a disc, 0.4–2.5× the
    expected area ``robot_area_px``, inside the frame).

    ``outline_px`` is the robot's outline in pixels (default the robot's,
    :func:`magctl.plant.outline.robot_outline`, at the pixel size that gives ``robot_area_px``).

    Line: the major principal axis of the darkness ``max(background − I, 0)`` over the blob grown by 3 px, turned
    back by the outline's own (:attr:`~magctl.plant.outline.RobotOutline.major_axis`, π/2: the robot is wider than
    long); the robot is mirror symmetric about its heading, so that is the heading's line. Sense: the outline is
    laid over the blob, its centroid on the blob's, at both headings of the line; its front notch, deeper than
    the rear one, makes one cover the blob better (a mirrored image changes nothing: the outline is symmetric).
    """
    if outline_px is None:
        robot = seen_shapes().robot
        outline_px = robot.scaled(math.sqrt(robot_area_px / robot.area))
    cands = [b for b in seg.blobs if not b.border and b.elongation > 1.2 and 0.4 <= b.area / robot_area_px <= 2.5]
    if not cands:
        return None
    blob = min(cands, key=lambda b: abs(math.log(b.area / robot_area_px)))
    box = tuple(slice(max(s.start - 4, 0), s.stop + 4) for s in blob.box)
    mask = seg.labels[box] == blob.label
    grown = ndimage.binary_dilation(mask, iterations=3)
    dark = np.clip(seg.background - seg.image[box], 0.0, None) * grown
    yy, xx = np.mgrid[box[0], box[1]].astype(float)
    cj, ci, axis = principal_axis(dark, xx, yy)
    line = axis - outline_px.major_axis
    covered = []
    for heading in (line, line + math.pi):
        c, s = math.cos(heading), math.sin(heading)
        gx, gy = outline_px.centroid
        origin = np.array([cj - (c * gx - s * gy), ci - (s * gx + c * gy)])
        covered.append((int(np.count_nonzero(mask & (robot_sdf(xx, yy, origin, heading, outline_px) < 0))),
                        heading, origin))
    (best, heading, origin), (other, _, _) = sorted(covered, key=lambda t: -t[0])
    return RobotPose(origin, float(_wrap(heading)), float(best - other))


# --- driving the rig ------------------------------------------------------------------------------------------
class _Tap:
    """The station's tracker with every frame it is given copied to ``sink`` first."""

    def __init__(self, tracker, sink):
        self._tracker, self._sink = tracker, sink

    def track(self, frame):
        self._sink(frame)
        return self._tracker.track(frame)

    def __getattr__(self, name):
        return getattr(self._tracker, name)


class RigSession:
    """Holds coil outputs on a station and collects its camera's frames (``with`` zeroes the coils at the end).

    In lock-step (the simulated lab) each frame is one :meth:`DeviceStation.step`; in real time the station's
    grabber thread delivers the frames, which a tap on its tracker copies here. Every frame the outputs are
    written again, so that the coil board's deadline never zeroes them.
    """

    def __init__(self, station):
        self.station = station
        self.period = float(getattr(station, "period", 1.0 / 30.0))
        self._frames: queue.Queue = queue.Queue()
        self._tracker = station.tracker
        station.tracker = _Tap(station.tracker, self._frames.put)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self) -> None:
        try:
            self.station.zero()
        finally:
            self.station.tracker = self._tracker

    def hold(self, setpoint, n_frames: int) -> list:
        """Write ``setpoint`` and keep it for ``n_frames`` frames; the frames the camera delivered meanwhile."""
        from magctl.rig.devices.base import DeviceError

        st, out = self.station, []
        while not self._frames.empty():  # frames from before this setpoint (real time: taken while we computed)
            self._frames.get_nowait()
        for _ in range(int(n_frames)):
            st.coils.write(setpoint)
            if st.lockstep:
                st.step((st.frame + 1) * self.period)
                while not self._frames.empty():
                    out.append(self._frames.get_nowait())
                continue
            try:
                out.append(self._frames.get(timeout=st.camera_timeout))
            except queue.Empty:
                raise DeviceError(st.camera.name, f"no frame for {st.camera_timeout:g} s (camera_timeout); "
                                                  "coils zeroed") from None
        return out


@dataclass
class _Setting:
    """One held coil setting and what was measured in it."""

    setpoint: object
    headings: list[float] = field(default_factory=list)   # image headings of the measured frames, rad
    poses: list[RobotPose] = field(default_factory=list)
    diameters: list[list[tuple]] = field(default_factory=list)  # per frame: (centre px, diameter px) per target


def _robot_area_px(pixel_size: float) -> float:
    return seen_shapes().robot.area / pixel_size**2


def _settle_frames(field_T: float, period: float, settle_taus: float) -> int:
    from magctl.plant._stickslip import load_robot
    from magctl.plant.robot import heading_time_constant

    tau = float(heading_time_constant(load_robot(), field_T))
    return max(2, math.ceil(settle_taus * tau / period)) + 1  # +1: the board and coils take up the new setpoint


def _measure(session: RigSession, setting: _Setting, settle: int, frames: int, robot_area: float,
             what: str, sphere_px: float | None = None) -> _Setting:
    """Hold ``setting``: ``settle`` frames, then measure the robot's heading (and the spheres) in ``frames``."""
    session.hold(setting.setpoint, settle)
    got = session.hold(setting.setpoint, frames)
    if not got:
        raise CalibrationError(f"{what}: the camera delivered no frame in {frames} frames")
    for frame in got:
        seg = segment(frame.image)
        pose = robot_pose(seg, robot_area)
        if pose is None:
            raise CalibrationError(
                f"{what}: robot not found in frame {frame.number} (no dark elongated blob of about "
                f"{robot_area:.0f} px, the robot's outline at the lab's pixel size, inside the frame; "
                f"{len(seg.blobs)} dark blobs)")
        if pose.margin < max(4.0, 0.01 * robot_area):
            raise CalibrationError(f"{what}: cannot tell the robot's front from its back in frame {frame.number} "
                                   f"(its outline covers the blob by {pose.margin:.0f} px more one way than the "
                                   f"other, under 1 % of its {robot_area:.0f} px: too few pixels across the robot?)")
        setting.poses.append(pose)
        setting.headings.append(pose.heading)
        if sphere_px is not None:
            setting.diameters.append(_sphere_diameters(seg, sphere_px))
    spread = np.degrees(np.ptp(np.unwrap(setting.headings))) if len(setting.headings) > 1 else 0.0
    if spread > SETTLE_TOLERANCE_DEG:
        raise CalibrationError(f"{what}: the robot's heading still changes ({spread:.2f}° over {len(got)} frames "
                               f"after {settle} frames of settling): give it more settling time (--settle-frames)")
    return setting


def _sphere_diameters(seg: Segmentation, expected_px: float) -> list[tuple[np.ndarray, float]]:
    """(centre px, diameter px) of every round blob of about ``expected_px`` that :func:`disc_diameter` measures."""
    out = []
    for b in seg.blobs:
        d_eq = 2.0 * math.sqrt(b.area / math.pi)
        if b.border or b.elongation > 1.15 or not 0.5 <= d_eq / expected_px <= 2.0:
            continue
        d = disc_diameter(seg, b)
        if d is not None:
            out.append((b.centre, d))
    return out


# --- camera ---------------------------------------------------------------------------------------------------
@dataclass
class CameraCalibration:
    """The result of :func:`calibrate_camera`.

    Attributes
    ----------
    calibration : PixelCalibration
        The fitted pixel calibration.
    pixel_size_se, rotation_se : float
        Standard errors (1σ), m and rad.
    diameter_px, diameter_se_px : float
        The target's mean diameter in pixels and its standard error.
    target_diameter : float
        The target's diameter, m.
    n_targets, n_target_images : int
        Distinct targets (spheres) measured and images of them used.
    directions, image_headings : ndarray
        The commanded field directions (glass, rad) and the robot's settled image headings (rad).
    residual_rms, other_rms : float
        Rms heading residual (rad) of the fit, and of the other mirror hypothesis.
    centre_px, centre_glass : ndarray
        The image centre (px) and the glass point it is pinned to (m).
    sources : dict
        key → source text of the calibration file.
    """

    calibration: object
    pixel_size_se: float
    rotation_se: float
    diameter_px: float
    diameter_se_px: float
    target_diameter: float
    n_targets: int
    n_target_images: int
    directions: np.ndarray
    image_headings: np.ndarray
    residual_rms: float
    other_rms: float
    centre_px: np.ndarray
    centre_glass: np.ndarray
    sources: dict

    def save(self, path, header: str = "") -> None:
        """Write the ``[calibration]`` table (``{ value, source }`` per key) that
        :meth:`~magctl.rig.devices.tracking.PixelCalibration.load` and :func:`magctl.config.load_file` read."""
        lines = [f"# {line}" for line in header.splitlines()] + ["[calibration]"]
        for key, value in self.calibration.to_params().items():
            text = ("true" if value else "false") if isinstance(value, bool) else repr(float(value))
            lines.append(f"{key} = {{ value = {text}, source = {_toml_str(self.sources[key])} }}")
        Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")

    def to_dict(self) -> dict:
        cal = self.calibration
        return {"pixel_size_um": cal.pixel_size * 1e6, "pixel_size_se_um": self.pixel_size_se * 1e6,
                "rotation_deg": math.degrees(cal.rotation), "rotation_se_deg": math.degrees(self.rotation_se),
                "mirror": cal.mirror, "origin_um": [v * 1e6 for v in cal.origin],
                "target_diameter_um": self.target_diameter * 1e6, "diameter_px": self.diameter_px,
                "diameter_se_px": self.diameter_se_px, "targets": self.n_targets,
                "target_images": self.n_target_images, "directions_deg": np.degrees(self.directions).tolist(),
                "image_headings_deg": np.degrees(self.image_headings).tolist(),
                "residual_rms_deg": math.degrees(self.residual_rms),
                "other_mirror_rms_deg": math.degrees(self.other_rms),
                "centre_px": self.centre_px.tolist(), "centre_um": (self.centre_glass * 1e6).tolist(),
                "sources": dict(self.sources)}


def fit_rotation(directions, image_headings) -> tuple[float, bool, float, float, float]:
    """Rotation and mirror from field directions ``φ_k`` (glass) and settled image headings ``θ_k``.

    For each sign ``σ`` (+1 not mirrored, −1 mirrored) the rotation minimising ``Σ (1 − cos(φ_k − σθ_k − r))``
    is the circular mean of ``φ_k − σθ_k``; the sign with the smaller rms residual wins. Returns
    ``(rotation, mirror, standard error, rms residual, rms residual of the other sign)``, rad.
    """
    phi, theta = np.asarray(directions, dtype=float), np.asarray(image_headings, dtype=float)
    fits = []
    for mirror in (False, True):
        d = phi + theta if mirror else phi - theta
        r = _circmean(d)
        res = _wrap(d - r)
        fits.append((float(np.sqrt(np.mean(res**2))), r, mirror, res))
    fits.sort(key=lambda f: f[0])
    (rms, r, mirror, res), other = fits[0], fits[1][0]
    se = float(np.std(res, ddof=1) / math.sqrt(res.size)) if res.size > 1 else math.nan
    return float(_wrap(r)), mirror, se, rms, other


def _no_targets(default_target: bool, target: float, expected_px: float, frames: int):
    what = ("spheres" if default_target else "round targets") + f" of {target * 1e6:g} µm"
    raise CalibrationError(f"no {what} found for the scale (round dark blobs of {0.5 * expected_px:.0f}–"
                           f"{2 * expected_px:.0f} px, clear of the robot and the frame's edge) in {frames} frames: "
                           "put them in view, or give the size of the targets in view (--target-diameter-um)")


def require_target(n_spheres: int | None, target_diameter: float | None) -> None:
    """The camera's scale needs targets of known size: spheres in the lab, or a target's diameter given."""
    if target_diameter is None and n_spheres == 0:
        raise CalibrationError("the scale needs targets of known size in view: this lab has no spheres "
                               "([tracker] n_spheres = 0); put spheres in view or give a calibration target's "
                               "diameter (--target-diameter-um)")


def calibrate_camera(station, *, target_diameter: float | None = None, field: float | None = None,
                     directions_deg: Sequence[float] = tuple(range(0, 360, 45)), frames: int = 3,
                     settle_frames: int | None = None, centre: Sequence[float] | None = None,
                     n_spheres: int | None = None, lab: str = "", progress: Callable[[str], None] | None = None
                     ) -> CameraCalibration:
    """Measure the camera's pixel size, rotation and mirror on a station (see the module docstring).

    Parameters
    ----------
    station : DeviceStation
    target_diameter : float, optional
        Diameter of the round targets in view, m; the spheres' (``models/sphere.toml``) by default.
    field : float, optional
        Static field magnitude, T; ``models/robot.toml`` [drive] static_field within the lab's limit.
    directions_deg : sequence of float
        Field directions in glass coordinates, visited in order (at least 3; consecutive ones at most 60° apart).
    frames : int
        Frames measured per direction (after settling).
    settle_frames : int, optional
        Frames to wait after each field step; :data:`SETTLE_TAUS` heading time constants by default.
    centre : (2,) sequence, optional
        Glass coordinates (m) of the image centre; where the station's current calibration puts it by default.
    n_spheres : int, optional
        Spheres the lab has (0 without a target diameter: an error before anything moves).
    lab : str
        The lab's name for the sources.
    progress : callable, optional
        Called with a line of text per step.
    """
    from magctl.config import load_model
    from magctl.rig.devices.base import setpoint_of
    from magctl.rig.devices.tracking import PixelCalibration
    from magctl.rig.interface import Command, CommandRejected

    require_target(n_spheres, target_diameter)
    dirs = np.radians(np.asarray(directions_deg, dtype=float))
    if dirs.size < 3:
        raise CalibrationError(f"rotation and mirror need at least 3 field directions, got {dirs.size}")
    steps = np.degrees(np.abs(_wrap(np.diff(dirs))))
    if steps.size and steps.max() > MAX_STEP_DEG + 1e-9:
        raise CalibrationError(f"consecutive field directions must be at most {MAX_STEP_DEG:g}° apart, got "
                               f"{steps.max():.1f}°")
    if frames < 1:
        raise CalibrationError("frames per direction must be >= 1")
    sphere_model = load_model("sphere").sphere
    default_target = target_diameter is None
    target = 2.0 * float(sphere_model.radius) if default_target else float(target_diameter)
    limits = station.limits
    if field is None:
        field = min(float(load_model("robot").drive.static_field), 0.9 * limits.b_static_max)
    period = float(station.period)
    settle = settle_frames if settle_frames is not None else _settle_frames(field, period, SETTLE_TAUS)
    nominal = getattr(station.tracker, "calibration", None) or PixelCalibration.identity()
    robot_area = _robot_area_px(nominal.pixel_size)
    expected_px = target / nominal.pixel_size
    say = progress or (lambda _text: None)

    def setting(phi: float):
        cmd = Command(field * np.array([math.cos(phi), math.sin(phi)]), 0.0, 0.0)
        try:
            limits.check(cmd)
        except CommandRejected as err:
            raise CalibrationError(f"field {field * 1e3:g} mT: {err}") from None
        return _Setting(setpoint_of(cmd, limits.coils))

    measured = []
    shape = None
    with RigSession(station) as session:
        # two warm-up directions 120° and 60° before the first: wherever the robot starts (even at the unstable
        # antipode of the first warm-up field), the second brings it within 120° of the field, so it follows
        for warm in (dirs[0] - 2 * math.pi / 3, dirs[0] - math.pi / 3):
            session.hold(setting(warm).setpoint, settle)
        for k, phi in enumerate(dirs):
            s = _measure(session, setting(phi), settle, frames, robot_area,
                         f"field direction {math.degrees(phi):g}°", expected_px)
            measured.append(s)
            if k == 0 and not any(s.diameters):
                _no_targets(default_target, target, expected_px, len(s.headings))
            say(f"field {math.degrees(phi):6.1f}°: robot at {math.degrees(_circmean(s.headings)):7.2f}° in the "
                f"image; {sum(len(d) for d in s.diameters)} target images")
        shape = station.camera.shape
    theta = np.array([_circmean(s.headings) for s in measured])
    rotation, mirror, rot_se, rms, other = fit_rotation(dirs, theta)
    if other < 3.0 * rms or other < math.radians(5.0):
        raise CalibrationError(f"the headings do not tell a mirrored image from a plain one (rms residual "
                               f"{math.degrees(rms):.2f}° vs {math.degrees(other):.2f}°): does the robot follow "
                               "the field?")
    if rms > math.radians(5.0):
        raise CalibrationError(f"the robot's headings do not follow the field directions by one rotation (rms "
                               f"residual {math.degrees(rms):.1f}°): check the coils and the robot")

    # targets: group the measurements of each target by position (they do not move: b_osc = 0)
    groups: list[tuple[np.ndarray, list[float]]] = []
    for s in measured:
        for frame_d in s.diameters:
            for centre_px, d in frame_d:
                for g in groups:
                    if np.hypot(*(g[0] - centre_px)) < 0.5 * expected_px:
                        g[1].append(d)
                        break
                else:
                    groups.append((centre_px, [d]))
    if not groups:
        _no_targets(default_target, target, expected_px, sum(len(s.headings) for s in measured))
    means = np.array([np.mean(g[1]) for g in groups])
    all_d = np.concatenate([g[1] for g in groups])
    d_px = float(means.mean())
    if means.size > 1:
        d_se = float(means.std(ddof=1) / math.sqrt(means.size))
    else:
        d_se = float(all_d.std(ddof=1) / math.sqrt(all_d.size)) if all_d.size > 1 else math.nan
    pixel = target / d_px
    pixel_se = target * d_se / d_px**2

    h, w = shape
    centre_px = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    pinned = centre is not None
    centre_glass = np.asarray(centre, dtype=float) if pinned else nominal.to_glass(centre_px)
    linear = PixelCalibration(pixel, rotation, mirror)
    origin = centre_glass - linear.to_glass(centre_px)
    cal = PixelCalibration(pixel, rotation, mirror, tuple(origin))

    where = f"magctl rig calibrate camera{f' on {lab}' if lab else ''}"
    n_dirs = dirs.size
    tgt = (f"the {target * 1e6:g} µm spheres (models/sphere.toml)" if default_target
           else f"a {target * 1e6:g} µm target (--target-diameter-um)")
    scatter = ("the scatter of the per-target means" if means.size > 1
               else "the scatter over the frames of one target: the noise only")
    count = f"{means.size} target{'s' if means.size > 1 else ''}, {all_d.size} images"
    sources = {
        "pixel_size_um": (f"measured: {pixel * 1e6:.5g} ± {pixel_se * 1e6:.2g} µm (1σ, {scatter}) by {where}: "
                          f"{tgt} measure {d_px:.3f} ± {d_se:.3f} px across ({count}; "
                          "blurred-disc edge fit); relative to the target's nominal size"),
        "rotation_deg": (f"measured: {math.degrees(rotation):.4g} ± {math.degrees(rot_se):.2g}° (1σ) by {where}: the "
                         f"robot's settled heading under a {field * 1e3:g} mT static field in {n_dirs} directions "
                         f"(coils only, the lab's coil map), least squares, rms residual {math.degrees(rms):.2f}°; "
                         "the robot's magnetisation taken along its body axis"),
        "mirror": (f"measured by {where}: the image heading turns {'against' if mirror else 'with'} the field "
                   f"(rms residual {math.degrees(rms):.2f}°; {math.degrees(other):.1f}° "
                   f"{'unmirrored' if mirror else 'mirrored'})"),
    }
    pin = ("given (--centre-um)" if pinned else "kept where the lab's previous calibration put it")
    for axis in ("x", "y"):
        sources[f"origin_{axis}_um"] = (
            f"assumed: the image centre, pixel ({centre_px[0]:g}, {centre_px[1]:g}), at glass "
            f"({centre_glass[0] * 1e6:.1f}, {centre_glass[1] * 1e6:.1f}) µm, {pin}; field directions do not "
            "show where the glass origin is")
    return CameraCalibration(cal, pixel_se, rot_se, d_px, d_se, target, int(means.size), int(all_d.size), dirs,
                             theta, rms, other, centre_px, centre_glass, sources)


# --- coils ----------------------------------------------------------------------------------------------------
def actuation_matrix(coils) -> np.ndarray:
    """``A`` (4 × n) of a :class:`~magctl.rig.interface.CoilMap`: the inverse of its allocation ``A⁺``."""
    return np.linalg.pinv(np.asarray(coils.pinv, dtype=float))


def adjusted_coil_map(coils, gain, angle):
    """``coils`` with each coil's field per ampere scaled by ``gain[k]`` and its in-plane part turned by
    ``angle[k]`` rad (columns of ``A``: ``[g R(α) a_xy; g a_z; g a_∇]``); current limits and clamp kept."""
    from magctl.rig.interface import CoilMap

    a = actuation_matrix(coils).copy()
    gain = np.asarray(gain, dtype=float).reshape(-1)
    angle = np.asarray(angle, dtype=float).reshape(-1)
    if gain.size != a.shape[1] or angle.size != a.shape[1]:
        raise CalibrationError(f"coil map has {a.shape[1]} coils, got {gain.size} gains and {angle.size} angles")
    c, s = np.cos(angle), np.sin(angle)
    xy = a[:2].copy()
    a[0], a[1] = c * xy[0] - s * xy[1], s * xy[0] + c * xy[1]
    a = a * gain[None, :]
    return CoilMap(np.linalg.pinv(a), coils.current_limit, coils.clamp_gradient, coils.names)


def in_plane_coils(coils, fraction: float = 0.05) -> np.ndarray:
    """Which coils make an in-plane field at the centre (more than ``fraction`` of the strongest one's)."""
    n = np.hypot(*actuation_matrix(coils)[:2])
    return n > fraction * n.max()


@dataclass
class CoilCalibration:
    """The result of :func:`calibrate_coils`: per coil (in the coil map's order).

    Attributes
    ----------
    names : list of str
    calibrated : ndarray of bool
        The in-plane coils (the vertical ones keep the model's column).
    gain, gain_se : ndarray
        Field per ampere relative to ``models/coils.toml`` and its standard error (1σ; 0 where not calibrated).
    angle, angle_se : ndarray
        Rotation of the in-plane field relative to the model, rad, and its standard error.
    direction, nominal_direction : ndarray
        Direction of the in-plane field of +1 A, rad: measured and the model's.
    field_per_ampere, nominal_field_per_ampere : ndarray
        In-plane field of 1 A at the centre, T: measured (the scale as ``scale`` says) and the model's.
    scale : str
        Where the absolute scale comes from.
    residual_rms : float
        Rms heading residual of the fit, rad.
    n_settings : int
        Coil settings measured.
    sources : dict
        (coil, key) → source text.
    """

    names: list
    calibrated: np.ndarray
    gain: np.ndarray
    gain_se: np.ndarray
    angle: np.ndarray
    angle_se: np.ndarray
    direction: np.ndarray
    nominal_direction: np.ndarray
    field_per_ampere: np.ndarray
    nominal_field_per_ampere: np.ndarray
    scale: str
    residual_rms: float
    n_settings: int
    sources: dict

    def apply(self, coils):
        """``coils`` (the model's map) with this calibration: :func:`adjusted_coil_map`."""
        return adjusted_coil_map(coils, self.gain, self.angle)

    def save(self, path, header: str = "") -> None:
        """Write ``[coil.<name>]`` tables (``gain_ratio``, ``angle_deg`` — what :func:`load_coil_calibration`
        applies — and, for reading, ``direction_deg`` and ``field_at_1A_mT``), each ``{ value, source }``."""
        lines = [f"# {line}" for line in header.splitlines()]
        for k, name in enumerate(self.names):
            lines += ["", f"[coil.{name}]"]
            values = {"gain_ratio": float(self.gain[k]), "angle_deg": math.degrees(self.angle[k])}
            if self.calibrated[k]:
                values["direction_deg"] = math.degrees(self.direction[k])
                values["field_at_1A_mT"] = self.field_per_ampere[k] * 1e3
            for key, value in values.items():
                lines.append(f"{key} = {{ value = {float(f'{value:.10g}')!r}, "
                             f"source = {_toml_str(self.sources[(name, key)])} }}")
        Path(path).write_text("\n".join(lines).lstrip("\n") + "\n", encoding="utf-8")

    def to_dict(self) -> dict:
        coils = {}
        for k, name in enumerate(self.names):
            coils[name] = {"calibrated": bool(self.calibrated[k]), "gain": float(self.gain[k]),
                           "gain_se": float(self.gain_se[k]), "angle_deg": math.degrees(self.angle[k]),
                           "angle_se_deg": math.degrees(self.angle_se[k])}
            if self.calibrated[k]:
                coils[name].update(direction_deg=math.degrees(self.direction[k]),
                                   model_direction_deg=math.degrees(self.nominal_direction[k]),
                                   field_at_1A_mT=self.field_per_ampere[k] * 1e3,
                                   model_field_at_1A_mT=self.nominal_field_per_ampere[k] * 1e3)
        return {"coils": coils, "scale": self.scale, "residual_rms_deg": math.degrees(self.residual_rms),
                "settings": self.n_settings}


def _plan_settings(a_xy: np.ndarray, plane: np.ndarray, current: float, max_step: float):
    """Coil current vectors around the circle: each in-plane coil alone, then its pair with the next coil (by
    field direction) at sub-steps of at most ``max_step`` rad, back to the first; with their nominal directions."""
    idx = np.flatnonzero(plane)
    dirs = np.arctan2(a_xy[1, idx], a_xy[0, idx])
    order = idx[np.argsort(dirs)]
    n = a_xy.shape[1]
    settings = []
    for pos, k in enumerate(order):
        nxt = order[(pos + 1) % order.size]
        ak, an = a_xy[:, k], a_xy[:, nxt]
        start, gap = math.atan2(ak[1], ak[0]), float(_wrap(math.atan2(an[1], an[0]) - math.atan2(ak[1], ak[0])))
        if gap <= 0:
            gap += 2 * math.pi
        if gap >= math.pi - 1e-6:
            raise CalibrationError("the in-plane coils do not surround the workspace (two neighbouring coils' "
                                   f"fields are {math.degrees(gap):.0f}° apart): the pairs cannot turn the field")
        parts = max(2, math.ceil(gap / max_step))
        for m in range(parts):
            psi = start + gap * m / parts
            # currents of coils k and nxt whose nominal field points at psi, the larger of the two at `current`
            sol = np.linalg.solve(np.column_stack([ak, an]), [math.cos(psi), math.sin(psi)])
            sol = current * sol / np.abs(sol).max()
            sol[np.abs(sol) < 1e-9 * current] = 0.0  # the single coil: no rounding residue on its neighbour
            i = np.zeros(n)
            i[k], i[nxt] = sol
            settings.append((i, psi))
    settings.append(settings[0])
    return settings


def _fit_coils(currents: np.ndarray, headings: np.ndarray, a_xy: np.ndarray, plane: np.ndarray):
    """Least-squares directions and log gains (geometric mean 1) of the in-plane coils; see the module docstring.

    Returns ``(beta, gain, beta_se, gain_se, rms)`` over the in-plane coils."""
    idx = np.flatnonzero(plane)
    m = idx.size
    norm = np.hypot(*a_xy[:, idx])
    beta0 = np.arctan2(a_xy[1, idx], a_xy[0, idx])
    cur = currents[:, idx]

    def unpack(p):
        beta, lg = p[:m], np.append(p[m:], -p[m:].sum())
        return beta, np.exp(lg)

    def resid(p):
        beta, g = unpack(p)
        bx = cur @ (g * norm * np.cos(beta))
        by = cur @ (g * norm * np.sin(beta))
        return _wrap(headings - np.arctan2(by, bx))

    fit = optimize.least_squares(resid, np.concatenate([beta0, np.zeros(m - 1)]), x_scale=0.05)
    beta, gain = unpack(fit.x)
    res = fit.fun
    dof = max(res.size - fit.x.size, 1)
    # a floor on the residual scale keeps a noiseless fit's errors from reading zero
    s2 = max(float(res @ res) / dof, math.radians(0.01) ** 2)
    jac = fit.jac
    try:
        cov = s2 * np.linalg.inv(jac.T @ jac)
    except np.linalg.LinAlgError:
        raise CalibrationError("the coil settings do not determine every in-plane coil's direction and gain") from None
    beta_se = np.sqrt(np.diag(cov)[:m])
    # log gains: the free m − 1 and the last one, minus their sum
    t = np.zeros((m, fit.x.size))
    t[: m - 1, m:] = np.eye(m - 1)
    t[m - 1, m:] = -1.0
    lg_cov = t @ cov @ t.T
    gain_se = gain * np.sqrt(np.diag(lg_cov))
    return _wrap(beta), gain, beta_se, gain_se, float(np.sqrt(np.mean(res**2)))


def hall_scale(field_per_ampere, names: Sequence[str], hall_mT_per_A: Mapping[str, float] | None
               ) -> tuple[float, str]:
    """The factor that puts the relative fields per ampere ``field_per_ampere`` (T/A, per coil) on the scale of
    Hall-probe readings (coil → mT/A; several: the geometric mean of their factors), and the scale's description;
    without readings 1 and the model's scale."""
    if not hall_mT_per_A:
        return 1.0, ("the model's (models/coils.toml): the in-plane gains' geometric mean is held at 1, the heading "
                     "does not show the field's magnitude")
    names = list(names)
    implied = [v * 1e-3 / float(field_per_ampere[names.index(k)]) for k, v in hall_mT_per_A.items()]
    readings = ", ".join(f"{k} {v:g} mT/A" for k, v in hall_mT_per_A.items())
    s = "s" if len(hall_mT_per_A) > 1 else ""
    return float(np.exp(np.mean(np.log(implied)))), f"Hall-probe reading{s} of {readings} at the centre"


def calibrate_coils(station, *, current: float | None = None, hall_mT_per_A: Mapping[str, float] | None = None,
                    frames: int = 3, settle_frames: int | None = None, max_step_deg: float = 25.0, model=None,
                    lab: str = "", progress: Callable[[str], None] | None = None) -> CoilCalibration:
    """Measure each in-plane coil's field direction and relative gain from the robot's heading (module docstring).

    Parameters
    ----------
    station : DeviceStation
        Its tracker's calibration turns image headings into glass headings (lab.toml ``[tracker] calibration``);
        its limits bound the currents and fields.
    current : float, optional
        The larger current of each setting, A; by default the one whose single-coil field is
        ``models/robot.toml`` [drive] static_field / √2, within half the smallest in-plane rating.
    hall_mT_per_A : mapping, optional
        Coil name → its in-plane field per ampere at the centre measured with a Hall probe, mT/A: sets the
        absolute scale (several: their geometric mean).
    frames : int
        Frames measured per setting.
    settle_frames : int, optional
        Frames to wait after each step; :data:`SETTLE_TAUS` heading time constants by default.
    max_step_deg : float
        The largest turn of the field between two settings, degrees.
    model : CoilMap, optional
        The map the result is relative to: ``models/coils.toml``'s (not the lab's, which may be calibrated already).
    """
    from magctl.config import load_model
    from magctl.rig.devices.base import CoilSetpoint, setpoint_of
    from magctl.rig.devices.tracking import PixelCalibration
    from magctl.rig.interface import CoilMap, Command, CommandRejected

    coils, limits = station.limits.coils, station.limits
    model = CoilMap.from_coils() if model is None else model
    names = list(coils.names)
    if list(model.names) != names:
        raise CalibrationError(f"the lab's coils ({', '.join(names)}) are not the model's "
                               f"({', '.join(model.names)})")
    a_xy = actuation_matrix(model)[:2]
    plane = in_plane_coils(model)
    if plane.sum() < 3:
        raise CalibrationError(f"the coil map has {int(plane.sum())} in-plane coils; the heading method needs 3 or "
                               "more around the workspace")
    hall = dict(hall_mT_per_A or {})
    for name in hall:
        if name not in names:
            raise CalibrationError(f"--field-mT-per-A {name}: no such coil (coils: {', '.join(names)})")
        if not plane[names.index(name)]:
            raise CalibrationError(f"--field-mT-per-A {name}: a vertical coil; the Hall reading sets the scale of "
                                   f"the in-plane coils ({', '.join(n for n, p in zip(names, plane) if p)})")
        if not (math.isfinite(hall[name]) and hall[name] > 0):
            raise CalibrationError(f"--field-mT-per-A {name}={hall[name]!r}: must be a field per ampere > 0 mT/A")
    norm = np.hypot(*a_xy)
    drive = float(load_model("robot").drive.static_field)
    rating = float(coils.current_limit[plane].min())
    if current is None:
        current = min(drive / math.sqrt(2.0) / float(norm[plane].mean()), 0.5 * rating)
    if not 0 < current <= rating:
        raise CalibrationError(f"current {current:g} A must be > 0 and within the in-plane coils' rating "
                               f"{rating:g} A")
    max_step = math.radians(min(max_step_deg, MAX_STEP_DEG))
    settings = _plan_settings(a_xy, plane, current, max_step)
    field_max = max(float(np.hypot(*(a_xy @ i))) for i, _ in settings)
    if field_max > limits.b_static_max * (1 + 1e-9):
        raise CalibrationError(f"current {current:g} A makes up to {field_max * 1e3:.3g} mT, above the lab's limit "
                               f"{limits.b_static_max * 1e3:g} mT: use a smaller --current-A")
    field_min = min(float(np.hypot(*(a_xy @ i))) for i, _ in settings)
    period = float(station.period)
    settle = settle_frames if settle_frames is not None else _settle_frames(field_min, period, SETTLE_TAUS)
    cal = getattr(station.tracker, "calibration", None) or PixelCalibration.identity()
    robot_area = _robot_area_px(cal.pixel_size)
    say = progress or (lambda _text: None)

    def field_setting(phi: float) -> _Setting:
        cmd = Command(field_min * np.array([math.cos(phi), math.sin(phi)]), 0.0, 0.0)
        try:
            limits.check(cmd)
        except CommandRejected as err:
            raise CalibrationError(f"aligning field {field_min * 1e3:.3g} mT: {err}") from None
        return _Setting(setpoint_of(cmd, coils))

    headings, rows = [], []
    with RigSession(station) as session:
        # coils off: where does the robot point? then turn the field from there to the first setting
        start = _measure(session, _Setting(CoilSetpoint.zero(len(names))), 1, 1, robot_area, "coils off")
        psi = cal.heading_to_glass(start.headings[0])
        target = settings[0][1]
        turn = float(_wrap(target - psi))
        n_steps = max(1, math.ceil(abs(turn) / math.radians(MAX_STEP_DEG)))
        for m in range(n_steps + 1):
            session.hold(field_setting(psi + turn * m / n_steps).setpoint, settle)
        for j, (i, psi_nom) in enumerate(settings):
            sp = CoilSetpoint(i, np.zeros_like(i), 0.0)
            try:
                sp.check(coils.current_limit, limits.freq_max, "calibration")
            except CommandRejected as err:
                raise CalibrationError(str(err)) from None
            what = ", ".join(f"{names[k]} {i[k]:+.3f} A" for k in np.flatnonzero(i))
            s = _measure(session, _Setting(sp), settle, frames, robot_area, what)
            h = cal.heading_to_glass(_circmean(s.headings))
            headings.append(h)
            rows.append(i)
            say(f"[{j + 1}/{len(settings)}] {what}: heading {math.degrees(h):7.2f}° (model "
                f"{math.degrees(float(_wrap(psi_nom))):7.2f}°)")
    currents, headings = np.array(rows), np.array(headings)
    beta, rel, beta_se, rel_se, rms = _fit_coils(currents, headings, a_xy, plane)
    idx = np.flatnonzero(plane)
    n = len(names)
    rel_all = np.ones(n)
    rel_all[idx] = rel
    factor, scale = hall_scale(rel_all * norm, names, hall)
    gain, gain_se, angle, angle_se = np.ones(n), np.zeros(n), np.zeros(n), np.zeros(n)
    gain[idx], gain_se[idx] = factor * rel, factor * rel_se
    nominal_dir = np.arctan2(a_xy[1], a_xy[0])
    nominal_dir[np.abs(nominal_dir) < 1e-12] = 0.0  # the model's +x coil: no −0 or 4e-15° in the report
    angle[idx], angle_se[idx] = _wrap(beta - nominal_dir[idx]), beta_se
    direction = nominal_dir.copy()
    direction[idx] = beta
    fpa = gain * norm
    for k in idx:
        if abs(angle[k]) > math.radians(30.0) or not 0.5 <= gain[k] / factor <= 2.0:
            raise CalibrationError(f"coil {names[k]}: its field points {math.degrees(angle[k]):+.1f}° from the model "
                                   f"with {gain[k] / factor:.2f}× its relative gain: check its wiring and polarity "
                                   "(the method assumes a coil map near models/coils.toml)")
    where = f"magctl rig calibrate coils{f' on {lab}' if lab else ''}"
    evidence = (f"the robot's settled heading over {len(settings)} single-coil and pair settings (≤ {current:.3g} A, "
                f"read through the lab's camera calibration), least squares, rms residual {math.degrees(rms):.2f}°")
    sources = {}
    for k, name in enumerate(names):
        if plane[k]:
            sources[(name, "gain_ratio")] = (f"measured: {gain[k]:.5g} ± {gain_se[k]:.2g} (1σ) by {where}: field "
                                             f"per ampere relative to models/coils.toml from {evidence}; scale: "
                                             f"{scale}")
            sources[(name, "angle_deg")] = (f"measured: {math.degrees(angle[k]):+.4g} ± "
                                            f"{math.degrees(angle_se[k]):.2g}° (1σ) by {where}: in-plane field "
                                            f"direction relative to models/coils.toml from {evidence}")
            sources[(name, "direction_deg")] = (f"measured by {where}: direction of the in-plane field of +1 A "
                                                f"(model {math.degrees(nominal_dir[k]):.4g}°); for reading, "
                                                "angle_deg is what is applied")
            sources[(name, "field_at_1A_mT")] = (f"measured by {where}: in-plane field of 1 A at the centre (model "
                                                 f"{norm[k] * 1e3:.4g} mT), scale: {scale}; for reading")
        else:
            why = ("model: models/coils.toml; not calibrated — a vertical coil makes no in-plane field at the "
                   "centre, so the robot's heading does not respond to it")
            sources[(name, "gain_ratio")] = sources[(name, "angle_deg")] = why
    return CoilCalibration(names, plane, gain, gain_se, angle, angle_se, direction, nominal_dir, fpa, norm, scale,
                           rms, len(settings), sources)


def load_coil_calibration(path, names: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    """The per-coil ``gain_ratio`` and ``angle_deg`` (→ rad) of a file :meth:`CoilCalibration.save` wrote, in the
    order of ``names``; a coil the file does not name keeps gain 1 and angle 0. Errors name the file, coil and
    key (:class:`CalibrationError`)."""
    path = Path(path)
    doc = read_toml(path, "coil calibration file", CalibrationError)
    table = doc.get("coil")
    if not isinstance(table, dict) or not table:
        raise CalibrationError(f"{path}: no [coil.<name>] tables (write it with magctl rig calibrate coils)")
    gain, angle = np.ones(len(names)), np.zeros(len(names))
    for name, entry in table.items():
        if name not in names:
            raise CalibrationError(f"{path} [coil.{name}]: no such coil (coils: {', '.join(names)})")
        if not isinstance(entry, dict):
            raise CalibrationError(f"{path} [coil.{name}]: must be a table")
        k = list(names).index(name)
        for key, low, high in (("gain_ratio", 0.0, math.inf), ("angle_deg", -180.0, 180.0)):
            if key not in entry:
                raise CalibrationError(f"{path} [coil.{name}] {key}: missing")
            value = entry[key]["value"] if isinstance(entry[key], dict) and "value" in entry[key] else entry[key]
            if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value) \
                    or not low < value <= high:
                raise CalibrationError(f"{path} [coil.{name}] {key}: {value!r} must be a number in "
                                       f"({low:g}, {high:g}]")
            if key == "gain_ratio":
                gain[k] = float(value)
            else:
                angle[k] = math.radians(float(value))
    return gain, angle
