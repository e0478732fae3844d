"""Sensing and servo: particle-filter tracker frame rate, and the servo + camera loop cost per trial-step.

* tracker: robot + 2 spheres on 640 × 480 rendered frames (rendering not timed), one core; target ≥ 30 frames/s
  (paper §II: tracking at 30 frames/sec).
* loop: servo + camera (positions mode, noise) + Kalman tracker + kinematic robot, B trials in lockstep; cost
  per trial-step at B = 1 and in a batch, target ≤ 10 µs per trial-step in the batch.
"""

from __future__ import annotations

import time

import numpy as np
from rows import fmt, row

from magctl.control.servo import Servo, servo_params
from magctl.core import simulate
from magctl.sensing.camera import camera_params, render_frame
from magctl.sensing.particle_filter import ImageTracker
from magctl.stability.servo import servo_step_diagram

T = 1.0 / 30.0
TRACKER_FPS_TARGET = 30.0
LOOP_US_TARGET = 10.0


def _tracker(frames: int) -> dict:
    p = camera_params()
    s = p.camera.pixel_size
    rng = np.random.default_rng(0)
    pos0, vel = np.array([1.0e-3, 1.2e-3]), np.array([400e-6, 100e-6]) * T
    sph0 = np.array([[2.0e-3, 3.0e-3], [3.0e-3, 2.0e-3]])
    data = []
    for k in range(frames):
        pos, h, sph = pos0 + k * vel, 0.3 + 0.01 * k, sph0 + k * np.array([[3e-6, 0.0], [0.0, -2e-6]])
        img = render_frame(pos, h, sph, p.render, pixel=s, width=640, height=480, noise=rng.standard_normal((480, 640)))
        data.append((img, pos, sph))
    trk = ImageTracker(p, n_spheres=2, pixel=s, dt=T, seed=1)
    trk.step(data[0][0], True)  # detection on the first frame, not timed
    err_r, err_s, found = [], [], True
    t0 = time.perf_counter()
    out = [trk.step(img, True) for img, _, _ in data[1:]]
    elapsed = time.perf_counter() - t0
    for (r_pos, _, _, r_sph, ok), (_, pos, sph) in zip(out, data[1:], strict=True):
        err_r.append(np.sum((r_pos - pos) ** 2) / s**2)
        err_s.append(np.sum((r_sph - sph) ** 2, axis=1) / s**2)
        found &= ok
    fps = (frames - 1) / elapsed
    return {"tracker_fps": fps, "tracker_fps_target": TRACKER_FPS_TARGET, "tracker_fps_met": fps >= TRACKER_FPS_TARGET,
            "robot_rms_px": float(np.sqrt(np.mean(err_r))), "sphere_rms_px": float(np.sqrt(np.mean(err_s))),
            "all_found": bool(found)}


def _loop(batch: int, steps: int) -> dict:
    servo = Servo("servo", params=servo_params("paper"))
    d = servo_step_diagram(servo, delay_frames=2, tracker_mode="kalman", predict=False, position_noise_px=0.3,
                           heading_noise=0.02, drop_probability=0.01, spheres=[[3e-3, 3e-3], [3.5e-3, 1e-3]])
    target = np.array([2e-3, 1e-3])

    def best(b, repeat):
        times = []
        for _ in range(repeat):
            t0 = time.perf_counter()
            simulate(d, steps, batch=b, seed=3, inputs={"target": target}, record=[])
            times.append(time.perf_counter() - t0)
        return min(times) / (b * steps) * 1e6

    one = best(1, 2)
    many = best(batch, 2)
    return {"loop_us_per_trial_step_b1": one, "loop_us_per_trial_step_batch": many, "loop_batch": batch,
            "loop_us_target": LOOP_US_TARGET, "loop_us_met": many <= LOOP_US_TARGET}


def run(quick: bool = False) -> dict:
    res = _tracker(20 if quick else 90)
    res.update(_loop(200 if quick else 2000, 60 if quick else 150))
    batch = f"{res['loop_batch']:,}"
    res["rows"] = [
        row("tracker on 640 × 480 frames, robot + 2 spheres, one core", res["tracker_fps"], "frames/s",
            ge=TRACKER_FPS_TARGET,
            note=f"robot {res['robot_rms_px']:.2g} px RMS, spheres {res['sphere_rms_px']:.2g} px RMS"
                 + ("" if res["all_found"] else "; lost in some frames")),
        row(f"servo + camera per trial-step in a {batch}-trial batch", res["loop_us_per_trial_step_batch"], "µs",
            le=LOOP_US_TARGET, note=f"B = 1: {fmt(res['loop_us_per_trial_step_b1'])} µs per step"),
    ]
    return res


if __name__ == "__main__":
    import json

    print(json.dumps(run(quick=True), indent=2))
