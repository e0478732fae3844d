"""The recorded-video check: frames rendered with known ground truth (:func:`magctl.sensing.camera.render_frame`:
optical blur, sensor noise), encoded to a video file, replayed through :class:`OpenCVCamera` and tracked by
:class:`FrameTracker` into observations in glass coordinates.

Two sequences, each in FFV1 (lossless) and MJPG (lossy), 240 × 160 px (1.8 × 1.2 mm at 7.5 µm; the tracker's cost
follows particles × objects, not the frame size):

* **drive** — the robot drives 1.2 px/frame, turning 45° on the way, past two spheres; frames 40–47 are missing
  from the file and the recording's frame numbers (a sidecar, :class:`OpenCVCamera` ``numbers``) still count them,
  so the tracker must find the drop from the numbers; from frame 75 the lighting drops to 0.7×. The tracker
  detects the objects itself on the first frame.
* **exit** — the robot backs out of the field of view at 400 µm/s (1.8 px/frame; the paper's speed), waits outside
  and drives back in, with one sphere in view throughout; frames 20–25 are blank (the camera delivered background
  only). The tracker starts from the true positions.

Checked: position error ≤ 0.5 px RMS over the tracked frames (robot and spheres separately), heading error ≤ 2° RMS
with the robot wholly in view, tracking loss exactly where it occurs — every blank frame, every frame with the robot
wholly outside the field, no frame with the robot wholly inside (a partly visible robot may be either), none after
the dropped stretch — and recovery after. The numbers measured are printed
(``pytest -s``). Deterministic: seeded noise and particle filters, no wall clock.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np
import pytest

pytest.importorskip("cv2")

from magctl.config import load_file  # noqa: E402
from magctl.core.errors import ParameterError  # noqa: E402
from magctl.rig.devices.base import Frame  # noqa: E402
from magctl.rig.devices.opencv_camera import OpenCVCamera  # noqa: E402
from magctl.rig.devices.tracking import FrameTracker, PixelCalibration  # noqa: E402
from magctl.rig.devices.video import write_video  # noqa: E402
from magctl.sensing.camera import camera_params, render_frame, robot_sdf, seen_shapes  # noqa: E402

P = camera_params()
R = P.render
S = P.camera.pixel_size
W, H = 240, 160
FPS = 30.0


@dataclass
class Sequence:
    """Ground truth in pixels (column, row) and image headings, and what happens to each frame."""

    robot: np.ndarray  # (n, 2)
    heading: np.ndarray  # (n,)
    spheres: np.ndarray  # (N, 2)
    dropped: set = field(default_factory=set)
    blank: set = field(default_factory=set)
    light: dict = field(default_factory=dict)  # frame → brightness factor

    @property
    def n(self) -> int:
        return len(self.heading)


@functools.cache
def outline_points() -> np.ndarray:
    """Body-frame points of a ¼-px grid inside the robot's outline (pixels): its area, point by point."""
    outline = seen_shapes().robot.scaled(1 / S)
    g = np.arange(-outline.reach - 1, outline.reach + 1, 0.25)
    xx, yy = np.meshgrid(g, g)
    return np.stack([xx, yy], axis=-1)[robot_sdf(xx, yy, (0.0, 0.0), 0.0, outline) < 0]


def visible_fraction(pos_px, heading) -> float:
    """Fraction of the robot's outline area inside the field (pixel areas ``[−½, W−½] × [−½, H−½]``)."""
    body = outline_points()
    c, s = np.cos(heading), np.sin(heading)
    x = pos_px[0] + c * body[:, 0] - s * body[:, 1]        # the inverse of robot_sdf's turn into the body frame
    y = pos_px[1] + s * body[:, 0] + c * body[:, 1]
    in_view = (x >= -0.5) & (x <= W - 0.5) & (y >= -0.5) & (y <= H - 0.5)
    return np.count_nonzero(in_view) / len(body)


def drive() -> Sequence:
    pos, h, robot, heading = np.array([45.0, 105.0]), 0.0, [], []
    for k in range(120):
        robot.append(pos.copy())
        heading.append(h)
        if 30 <= k < 60:
            h -= math.radians(1.5)
        pos = pos + 1.2 * np.array([math.cos(h), math.sin(h)])
    return Sequence(np.array(robot), np.array(heading), np.array([[200.0, 120.0], [40.0, 35.0]]),
                    dropped=set(range(40, 48)), light={k: 0.7 for k in range(75, 120)})


def exit_view() -> Sequence:
    x = [90.0 - 1.8 * k if k < 75 else -45.0 if k < 85 else -45.0 + 1.8 * (k - 85) for k in range(150)]
    robot = np.stack([np.array(x), np.full(150, 80.0)], axis=1)
    return Sequence(robot, np.zeros(150), np.array([[190.0, 40.0]]), blank=set(range(20, 26)))


def record(seq: Sequence, path, codec: str) -> list[int]:
    """Render, encode; the frame numbers of the frames in the file (the recording's sidecar)."""
    rng = np.random.default_rng(7)
    frames, numbers = [], []
    for k in range(seq.n):
        noise = rng.standard_normal((H, W))
        if k in seq.dropped:
            continue
        if k in seq.blank:
            img = R.background + R.noise_sigma * noise
        else:
            img = render_frame(seq.robot[k] * S, seq.heading[k], seq.spheres * S, R, pixel=S, width=W, height=H,
                               noise=noise)
        frames.append(np.clip(img * seq.light.get(k, 1.0), 0.0, 1.0))
        numbers.append(k)
    write_video(path, frames, FPS, codec)
    return numbers


@dataclass
class Replay:
    numbers: list
    lost: dict
    robot_err: dict  # frame → px, tracked frames
    sphere_err: dict  # frame → (N,) px
    heading_err: dict  # frame → deg
    tracker: FrameTracker

    def rms(self, errs: dict, frames=None) -> float:
        vals = [np.atleast_1d(errs[k]) for k in (errs if frames is None else frames) if k in errs]
        return float(np.sqrt(np.mean(np.square(np.concatenate(vals))))) if vals else math.nan


def replay(seq: Sequence, path, numbers, *, init: bool) -> Replay:
    kw = {"init_robot": seq.robot[0] * S, "init_heading": seq.heading[0], "init_spheres": seq.spheres * S} \
        if init else {}
    trk = FrameTracker(len(seq.spheres), dt=1 / FPS, seed=1, **kw)
    out = Replay([], {}, {}, {}, {}, trk)
    order = None
    with OpenCVCamera(path, numbers=numbers, name="replay") as cam:
        while (frame := cam.grab(5.0)) is not None:
            obs = trk.track(frame)
            k = frame.number
            assert obs.frame == k and obs.t == pytest.approx(k / FPS)
            out.numbers.append(k)
            out.lost[k] = obs.lost
            if obs.lost:
                continue
            est = obs.spheres_est / S
            if order is None:  # detected spheres come in the tracker's order: match them once
                order = [int(np.argmin(np.linalg.norm(seq.spheres - e, axis=1))) for e in est]
                assert sorted(order) == list(range(len(seq.spheres)))
            out.robot_err[k] = float(np.linalg.norm(obs.robot_est / S - seq.robot[k]))
            out.sphere_err[k] = np.linalg.norm(est - seq.spheres[order], axis=1)
            out.heading_err[k] = abs(math.degrees(math.remainder(obs.heading_est - seq.heading[k], 2 * math.pi)))
        assert cam.ended
    return out


CODECS = ["FFV1", "MJPG"]


@pytest.mark.parametrize("codec", CODECS)
def test_drive_with_dropped_frames_a_turn_and_a_lighting_change(tmp_path, codec):
    seq = drive()
    assert min(visible_fraction(p, h) for p, h in zip(seq.robot, seq.heading)) == 1.0
    numbers = record(seq, tmp_path / f"drive.{codec}.avi", codec)
    run = replay(seq, tmp_path / f"drive.{codec}.avi", numbers, init=False)
    print(f"\ndrive {codec}: robot {run.rms(run.robot_err):.3f} px RMS (max {max(run.robot_err.values()):.2f}), "
          f"spheres {run.rms(run.sphere_err):.3f} px RMS, heading {run.rms(run.heading_err):.2f}° RMS; first frame "
          f"after the drop {run.robot_err.get(48, math.nan):.2f} px, dropped {run.tracker.dropped}")
    assert run.numbers == numbers and run.tracker.dropped == len(seq.dropped)
    # found again in the first frame after the drop, though the robot turned 12° in the frames missing
    assert not any(run.lost.values()), f"lost at {[k for k, v in run.lost.items() if v]}"
    assert run.rms(run.robot_err) <= 0.5
    assert run.rms(run.sphere_err) <= 0.5
    assert run.rms(run.heading_err) <= 2.0
    # the lighting step changes nothing: the same accuracy either side of it
    before, after = range(48, 75), range(75, 120)
    assert run.rms(run.robot_err, after) <= 0.5 and run.rms(run.robot_err, before) <= 0.5


@pytest.mark.parametrize("codec", CODECS)
def test_loss_where_the_robot_leaves_the_view_and_on_blank_frames(tmp_path, codec):
    seq = exit_view()
    vis = np.array([visible_fraction(p, h) for p, h in zip(seq.robot, seq.heading)])
    outside, inside = set(np.flatnonzero(vis == 0.0)), set(np.flatnonzero(vis == 1.0))
    assert outside and inside and not (outside & seq.blank)
    numbers = record(seq, tmp_path / f"exit.{codec}.avi", codec)
    run = replay(seq, tmp_path / f"exit.{codec}.avi", numbers, init=True)
    lost = {k for k, v in run.lost.items() if v}
    back = min(k for k in inside if k > max(outside))
    partial = sorted(set(range(seq.n)) - outside - inside)
    reacquired = min(k for k in run.robot_err if k > max(outside))
    print(f"\nexit {codec}: robot {run.rms(run.robot_err):.3f} px RMS over tracked frames (max "
          f"{max(run.robot_err.values()):.2f}), {run.rms(run.robot_err, inside):.3f} px with the robot wholly in view,"
          f" {run.rms(run.robot_err, partial):.3f} px partly in view; spheres {run.rms(run.sphere_err):.3f} px RMS; "
          f"heading {run.rms(run.heading_err, inside):.2f}° RMS wholly in view; lost {sorted(lost)}; re-acquired at "
          f"frame {reacquired} ({vis[reacquired]:.0%} in view)")
    assert run.numbers == list(range(seq.n)) and run.tracker.dropped == 0
    assert seq.blank <= lost and run.tracker.blanks == len(seq.blank)
    assert outside <= lost, f"not lost while outside: {sorted(outside - lost)}"
    assert not (inside - seq.blank) & lost, f"lost while wholly in view: {sorted((inside - seq.blank) & lost)}"
    # recovered: tracked from the first frame after the blank stretch, and again before the robot is wholly back
    assert not run.lost[max(seq.blank) + 1] and reacquired <= back
    assert run.rms(run.heading_err, inside) <= 2.0      # never half-turned, after the blank stretch or re-entry
    assert run.rms(run.robot_err) <= 0.5
    assert run.rms(run.sphere_err) <= 0.5


# --- the frame → observation glue ----------------------------------------------------------------------------
def _frame(k, robot=(60.0, 80.0), heading=0.0, spheres=((180.0, 80.0),), seed=0, scale=1.0):
    rng = np.random.default_rng(seed + k)
    img = render_frame(np.asarray(robot) * S, heading, np.asarray(spheres) * S, R, pixel=S, width=W, height=H,
                       noise=rng.standard_normal((H, W)))
    return Frame(np.clip(img * scale, 0, 1), k / FPS, k)


def test_damaged_frames_are_lost_frames_not_exceptions():
    trk = FrameTracker(1, init_robot=np.array([60.0, 80.0]) * S, init_spheres=np.array([[180.0, 80.0]]) * S)
    assert not trk.track(_frame(0)).lost
    nan = _frame(1).image.copy()
    nan[10, 10] = np.nan
    inf = _frame(2).image.copy()
    inf[5, :] = np.inf
    for k, img in ((1, nan), (2, inf), (3, np.full((H, W + 1), 0.8)), (4, np.zeros((3, H, W))),
                   (5, np.zeros((H, W))), (6, np.ones((H, W)))):
        obs = trk.track(Frame(img, k / FPS, k))
        assert obs.lost and obs.frame == k and np.all(np.isfinite(obs.robot_est))
    assert trk.damaged == 4 and trk.blanks == 2
    obs = trk.track(_frame(7))
    assert not obs.lost and np.linalg.norm(obs.robot_est / S - [60.0, 80.0]) < 1.0


def test_detection_waits_for_a_frame_that_shows_the_objects():
    trk = FrameTracker(1)  # no initial positions: the tracker finds the objects itself
    speck = np.full((H, W), R.background)
    speck[40:70, 40:70] = R.sphere_level  # a sphere-dark blob and a one-pixel robot-dark speck: nothing to detect
    speck[100, 100] = R.robot_level
    assert trk.track(Frame(speck, 0.0, 0)).lost and not trk.tracker.started
    obs = trk.track(_frame(1))
    assert not obs.lost and np.linalg.norm(obs.robot_est / S - [60.0, 80.0]) < 1.0
    assert np.linalg.norm(obs.spheres_est / S - [[180.0, 80.0]]) < 1.0


def test_dropped_frames_step_the_motion_model():
    """A robot moving 1.5 px/frame, every other frame lost in transit: the drops are counted and the tracker stays
    on it (its estimate moves on through the missing frames)."""
    trk = FrameTracker(1, init_robot=np.array([60.0, 80.0]) * S, init_spheres=np.array([[180.0, 80.0]]) * S)
    errs = []
    for k in range(0, 40):
        if k > 10 and k % 2:
            continue
        obs = trk.track(_frame(k, robot=(60.0 + 1.5 * k, 80.0)))
        assert not obs.lost
        errs.append(np.linalg.norm(obs.robot_est / S - [60.0 + 1.5 * k, 80.0]))
    assert trk.dropped == 14
    assert np.sqrt(np.mean(np.square(errs))) < 0.5


def test_blank_observation_and_lost_frame():
    trk = FrameTracker(2, init_robot=[1e-3, 2e-3], init_heading=0.3, init_spheres=[[2e-3, 1e-3], [3e-3, 1e-3]])
    obs = trk.blank(0.0, 0)
    assert obs.lost and obs.robot_est == pytest.approx([1e-3, 2e-3]) and obs.heading_est == pytest.approx(0.3)
    assert obs.spheres_est.shape == (2, 2) and obs.currents.shape == (6,)
    assert trk.lost_frame().lost
    empty = FrameTracker(0)
    assert empty.blank(1.0, 3).spheres_est.shape == (0, 2)


# --- the pixel calibration -------------------------------------------------------------------------------------
def test_identity_calibration_is_the_renderers_coordinates():
    cal = PixelCalibration.identity()
    assert cal.pixel_size == pytest.approx(7.5e-6) and cal.rotation == 0 and not cal.mirror
    assert cal.to_glass([[3.0, 2.0]]) == pytest.approx(np.array([[3 * S, 2 * S]]))
    assert cal.heading_to_glass(0.4) == pytest.approx(0.4)


@pytest.mark.parametrize("mirror", [False, True])
def test_calibration_maps_points_and_headings_consistently(mirror):
    cal = PixelCalibration(7.0e-6, math.radians(4.0), mirror, (1e-4, -2e-4))
    px = np.random.default_rng(0).uniform(0, 640, (20, 2))
    np.testing.assert_allclose(cal.to_pixels(cal.to_glass(px)), px, atol=1e-9)
    # a heading is the direction between two points: mapped as the points are
    for theta in (0.0, 0.7, -2.5):
        a = np.array([100.0, 50.0])
        b = a + 10 * np.array([math.cos(theta), math.sin(theta)])
        ga, gb = cal.to_glass(a), cal.to_glass(b)
        assert math.atan2(*(gb - ga)[::-1]) == pytest.approx(cal.heading_to_glass(theta))
        assert cal.heading_to_image(cal.heading_to_glass(theta)) == pytest.approx(theta)
    # the scale is the pixel size
    assert np.linalg.norm(cal.to_glass([1.0, 0.0]) - cal.to_glass([0.0, 0.0])) == pytest.approx(7.0e-6)


def test_calibration_params_round_trip_and_key_rules(tmp_path):
    cal = PixelCalibration(7.2e-6, math.radians(-3.0), True, (5e-5, 6e-5))
    table = cal.to_params()
    assert set(table) == {"pixel_size_um", "rotation_deg", "mirror", "origin_x_um", "origin_y_um"}
    back = PixelCalibration.from_params(table)
    assert back.mirror and back.pixel_size == pytest.approx(cal.pixel_size)
    assert back.rotation == pytest.approx(cal.rotation) and back.origin == pytest.approx(cal.origin)
    entries = {k: {"value": v, "source": "measured"} for k, v in table.items()}
    assert PixelCalibration.from_params(entries) == back
    assert PixelCalibration.from_params({"rotation_rad": 0.1}).rotation == pytest.approx(0.1)
    assert PixelCalibration.from_params(P.camera) == PixelCalibration.identity()  # [camera]: its pixel, rest default
    for bad, word in (({"mirror_bool": True}, "mirror_bool"), ({"pixel_size_px": 2.0}, "pixel_size_px"),
                      ({"mirror": 1}, "mirror"), ({"rotation_deg": "4"}, "not a number"),
                      ({"pixel_size_um": -1.0}, "pixel size")):
        with pytest.raises(ParameterError, match=word):
            PixelCalibration.from_params(bad)
    path = tmp_path / "calibration.toml"
    cal.save(path, source='measured: "targets" on the glass')
    assert PixelCalibration.load(path) == back
    assert load_file(path).calibration.mirror is True  # magctl's own loader reads it too
    with pytest.raises(ParameterError, match="not found"):
        PixelCalibration.load(tmp_path / "none.toml")


def test_tracker_reports_glass_coordinates_through_a_turned_mirrored_calibration():
    """Frames filmed through a camera turned 4° and mirrored (as the simulated camera films the world): with that
    calibration the observations are where the world has the objects."""
    cal = PixelCalibration(S, math.radians(4.0), True, (0.2e-3, 1.3e-3))  # glass y up the image
    robot_g, heading_g, spheres_g = np.array([0.8e-3, 0.7e-3]), 0.5, np.array([[1.5e-3, 0.5e-3]])
    trk = FrameTracker(1, calibration=cal, init_robot=robot_g, init_heading=heading_g, init_spheres=spheres_g)
    rng = np.random.default_rng(3)
    errs, herrs = [], []
    for k in range(20):
        pos_g = robot_g + k * np.array([1.0e-6, 5.0e-6])
        img = render_frame(cal.to_pixels(pos_g) * S, cal.heading_to_image(heading_g), cal.to_pixels(spheres_g) * S,
                           R, pixel=S, width=W, height=H, noise=rng.standard_normal((H, W)))
        obs = trk.track(Frame(np.clip(img, 0, 1), k / FPS, k))
        assert not obs.lost
        errs.append(np.linalg.norm(obs.robot_est - pos_g) / S)
        herrs.append(math.remainder(obs.heading_est - heading_g, 2 * math.pi))
        assert np.linalg.norm(obs.spheres_est - spheres_g) / S < 0.5
    assert np.sqrt(np.mean(np.square(errs))) < 0.5
    assert math.degrees(np.sqrt(np.mean(np.square(herrs)))) < 2.0
