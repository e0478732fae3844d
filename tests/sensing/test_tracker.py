"""Tracker: batched Kalman against filterpy, prediction across the latency, loss, particle filter on frames."""

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter

from magctl.core import Constant, Diagram, Integrator, ParameterError, simulate
from magctl.sensing.camera import Camera, camera_params, render_frame
from magctl.sensing.particle_filter import DetectionError, ImageTracker
from magctl.sensing.tracker import Tracker, cv_model

T = 1.0 / 30.0


def _meas_inputs(z_robot, z_spheres, valid, heading=None):
    b = z_robot.shape[0]
    return {"robot_meas": z_robot, "heading_meas": np.zeros(b) if heading is None else heading,
            "spheres_meas": z_spheres, "valid": valid}


def test_batched_kalman_matches_filterpy_per_trial():
    rng = np.random.default_rng(0)
    B, steps = 5, 60
    trk = Tracker("trk", n_spheres=1, mode="kalman")
    st = trk.initial_state(B)
    truth = np.cumsum(rng.normal(0, 5e-6, (steps, B, 2, 2)), axis=0) + 1e-3
    valid = rng.random((steps, B)) > 0.2
    valid[0] = True
    z = truth + rng.normal(0, 3e-6, truth.shape)
    F, Q = cv_model(T, trk.params.tracker.robot_accel_noise)
    _, Qs = cv_model(T, trk.params.tracker.sphere_accel_noise)
    ref = {}
    for b in range(B):
        for m in range(2):
            for a in range(2):
                kf = KalmanFilter(dim_x=2, dim_z=1)
                kf.F, kf.H, kf.R = F, np.array([[1.0, 0.0]]), np.array([[trk.R]])
                kf.Q = Q if m == 0 else Qs
                kf.x = np.array([z[0, b, m, a], 0.0])
                kf.P = np.diag([trk.R, 4e-4**2])
                ref[b, m, a] = kf
    for k in range(steps):
        u = _meas_inputs(z[k, :, 0], z[k, :, 1:], valid[k])
        out = trk.output(st, u)
        st = trk.update(st, u)
        if k == 0:
            continue
        for (b, m, a), kf in ref.items():
            kf.predict()
            if valid[k, b]:
                kf.update(np.array([z[k, b, m, a]]))
            est = out["robot_est"][b, a] if m == 0 else out["spheres_est"][b, 0, a]
            assert est == pytest.approx(kf.x[0], abs=1e-12)
            if m == 0:
                assert out["velocity_est"][b, a] == pytest.approx(kf.x[1], abs=1e-10)
            np.testing.assert_allclose(st["P"][b, m], kf.P, rtol=1e-9, atol=1e-20)


def _loop(tracker, latency, steps=150, v=(3e-4, -2e-4), noise_px=0.3, drop=0.0, batch=8):
    cam = Camera("camera", n_spheres=1, latency_frames=latency, position_noise_px=noise_px, drop_probability=drop)
    blocks = [Integrator("robot", shape=(2,), in_unit="m/s", out_unit="m", initial=[1.0e-3, 2.5e-3]),
              Constant("h", 0.0, unit="rad"), Constant("s", [[3e-3, 1e-3]], shape=(1, 2), unit="m"), cam, tracker]
    conns = [("robot.y", "camera.position"), ("h.y", "camera.heading"), ("s.y", "camera.spheres"),
             ("camera.robot_meas", "trk.robot_meas"), ("camera.heading_meas", "trk.heading_meas"),
             ("camera.spheres_meas", "trk.spheres_meas"), ("camera.valid", "trk.valid")]
    d = Diagram("loop", blocks, conns, inputs={"v": "robot.u"})
    return simulate(d, steps, batch=batch, seed=5, inputs={"v": list(v)})


def test_kalman_prediction_beats_raw_delayed_measurement():
    latency = 3
    res = _loop(Tracker("trk", mode="kalman", predict_frames=latency), latency)
    truth = res["robot.y"][:, 40:]
    err_kf = np.sqrt(np.mean(np.sum((res["trk.robot_est"][:, 40:] - truth) ** 2, axis=-1)))
    err_raw = np.sqrt(np.mean(np.sum((res["camera.robot_meas"][:, 40:] - truth) ** 2, axis=-1)))
    # the raw measurement lags by latency·T·|v| = 36 µm; the prediction removes the lag
    assert err_raw == pytest.approx(latency * T * np.hypot(3e-4, -2e-4), rel=0.1)
    assert err_kf < 0.5 * err_raw
    vel = res["trk.velocity_est"][:, 60:].mean(axis=(0, 1))
    np.testing.assert_allclose(vel, [3e-4, -2e-4], atol=1e-5)


def test_loss_reported_after_coasting_and_nan_mode():
    trk = Tracker("trk", mode="kalman", on_loss="nan")
    st = trk.initial_state(1)
    z, zs = np.array([[1e-3, 1e-3]]), np.array([[[2e-3, 2e-3]]])
    lost = []
    for k in range(12):
        u = _meas_inputs(z, zs, np.array([k < 3]))
        out = trk.output(st, u)
        st = trk.update(st, u)
        lost.append(bool(out["lost"][0]))
        if out["lost"][0]:
            assert np.isnan(out["robot_est"]).all() and np.isnan(out["spheres_est"]).all()
        else:
            assert np.isfinite(out["robot_est"]).all()
    coast = trk.max_coast
    assert lost == [False] * (3 + coast) + [True] * (12 - 3 - coast)


def test_not_lost_before_first_frame_is_lost():
    trk = Tracker("trk", mode="raw")
    st = trk.initial_state(2)
    u = _meas_inputs(np.zeros((2, 2)), np.zeros((2, 1, 2)), np.array([False, True]))
    out = trk.output(st, u)
    np.testing.assert_array_equal(out["lost"], [True, False])


@pytest.mark.parametrize("kw, word", [({"mode": "magic"}, "mode"), ({"on_loss": "guess"}, "on_loss"),
                                      ({"predict_frames": -1}, "predict_frames")])
def test_bad_tracker_parameters(kw, word):
    with pytest.raises(ParameterError, match=word):
        Tracker("trk", **kw)


# --- particle filter on rendered frames ---------------------------------------------------------------
def _frames(n, rng, p, pos0, vel, h0, dh, sph0, sph_vel):
    s = p.camera.pixel_size
    for k in range(n):
        pos, h, sph = pos0 + k * vel, h0 + k * dh, sph0 + k * sph_vel
        img = render_frame(pos, h, sph, p.render, pixel=s, width=640, height=480,
                           noise=rng.standard_normal((480, 640)))
        yield img, pos, h, sph


def test_particle_filter_within_one_pixel_rms_on_moving_robot_and_sphere():
    p = camera_params()
    s = p.camera.pixel_size
    rng = np.random.default_rng(1)
    trk = ImageTracker(p, n_spheres=1, pixel=s, dt=T, seed=2)
    err_r, err_s, err_h = [], [], []
    # robot at 400 µm/s turning slowly; the sphere drifts at 60 µm/s (being pushed by flow)
    for img, pos, h, sph in _frames(60, rng, p, np.array([1.0e-3, 1.2e-3]), np.array([400e-6, 100e-6]) * T,
                                    0.3, 0.01, np.array([[3.0e-3, 2.2e-3]]), np.array([[60e-6, 0.0]]) * T):
        r_pos, r_h, _, r_sph, found = trk.step(img, True)
        assert found
        err_r.append(np.sum((r_pos - pos) ** 2) / s**2)
        err_s.append(np.sum((r_sph - sph) ** 2) / s**2)
        err_h.append(np.angle(np.exp(1j * (r_h - h))))
    assert np.sqrt(np.mean(err_r)) <= 1.0
    assert np.sqrt(np.mean(err_s)) <= 1.0
    assert np.degrees(np.sqrt(np.mean(np.square(err_h)))) < 3.0


def test_particle_tracker_block_reports_loss_when_robot_leaves_frame():
    cam = Camera("camera", mode="images", n_spheres=1, latency_frames=0)
    trk = Tracker("trk", mode="particle", n_spheres=1)
    blocks = [Integrator("robot", shape=(2,), in_unit="m/s", out_unit="m", initial=[4.55e-3, 1.8e-3]),
              Constant("h", 0.0, unit="rad"), Constant("s", [[1.5e-3, 1.5e-3]], shape=(1, 2), unit="m"), cam, trk]
    conns = [("robot.y", "camera.position"), ("h.y", "camera.heading"), ("s.y", "camera.spheres"),
             ("camera.image", "trk.image"), ("camera.valid", "trk.valid")]
    d = Diagram("loop", blocks, conns, inputs={"v": "robot.u"})
    res = simulate(d, 40, seed=0, inputs={"v": [1.5e-3, 0.0]}, record=["trk.lost", "robot.y", "trk.robot_est"])
    lost = res["trk.lost"][0]
    x = res["robot.y"][0, :, 0]
    assert not lost[:3].any()
    # fully outside the frame (robot centre beyond the edge by more than half its length) → lost
    gone = x > cam.field_of_view[0] + 240e-6
    assert gone.any() and lost[np.flatnonzero(gone)[0] + trk.max_coast + 1:].all()
    in_frame = ~lost & (x < cam.field_of_view[0] - 240e-6)
    err = np.linalg.norm(res["trk.robot_est"][0][in_frame] - res["robot.y"][0][in_frame], axis=1)
    assert err.max() < 2 * 7.5e-6


def test_detection_error_when_objects_missing():
    p = camera_params()
    s = p.camera.pixel_size
    img = render_frame(np.array([1e-3, 1e-3]), 0.0, np.zeros((0, 2)), p.render, pixel=s, width=640, height=480)
    trk = ImageTracker(p, n_spheres=2, pixel=s, dt=T)
    with pytest.raises(DetectionError, match="found 0 sphere-sized blobs"):
        trk.step(img, True)
    with pytest.raises(DetectionError, match="no robot"):
        trk.step(np.full((480, 640), p.render.background), True)
