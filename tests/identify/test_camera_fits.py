"""Camera identification: position noise through the quantiser and the Kalman tracker, frame lag from command
onsets, dropped frames from the frame counter. Logs are made with magctl's own blocks at known values."""

import dataclasses
import re

import numpy as np
import pytest

from magctl.core import Diagram, simulate
from magctl.identify.camera import drop_rate, latency_from_commands, noise_from_stationary
from magctl.identify.estimate import IdentifyError, NotIdentified
from magctl.plant._stickslip import load_robot
from magctl.plant.robot import StickSlipRobot
from magctl.sensing.camera import Camera, camera_params
from magctl.sensing.tracker import Tracker

PIXEL = camera_params().camera.pixel_size
SENSOR_WIRES = [("camera.robot_meas", "tracker.robot_meas"), ("camera.heading_meas", "tracker.heading_meas"),
                ("camera.spheres_meas", "tracker.spheres_meas"), ("camera.valid", "tracker.valid")]
NO_SPHERES = np.zeros((0, 2))


# --- position noise -----------------------------------------------------------------------------------------
def stationary_windows(sigma_px, lengths, seed):
    """``robot_est`` of a still robot, one window per length, each at its own place in the view (random whole
    and sub-pixel position), camera noise σ and the tracker's R at σ, as on the rig."""
    rng = np.random.default_rng(seed)
    n = len(lengths)
    pos = PIXEL * (rng.integers(100, 400, (n, 2)) + rng.random((n, 2)))
    cam = Camera(n_spheres=0, latency_frames=0, position_noise_px=sigma_px, drop_probability=0.0)
    trk = Tracker(n_spheres=0, position_noise_px=sigma_px)
    d = Diagram("still", [cam, trk], SENSOR_WIRES, inputs={"position": "camera.position", "heading": "camera.heading",
                                                           "spheres": "camera.spheres"},
                outputs={"robot_est": "tracker.robot_est"})
    T = max(lengths)
    res = simulate(d, T, batch=n, seed=seed, inputs={"position": np.broadcast_to(pos[:, None], (n, T, 2)),
                                                     "heading": 0.0, "spheres": NO_SPHERES})
    return [res.outputs["robot_est"][i, :m] for i, m in enumerate(lengths)]


def test_noise_recovered_through_quantiser_and_tracker():
    windows = stationary_windows(0.6, [150, 200, 250, 300, 180], seed=7)  # the fit's own seed is 20240611
    est = noise_from_stationary(windows, "5 synthetic windows")
    assert est.name == "camera.toml:camera.position_noise_px"
    assert 0 < est.uncertainty < 0.1
    assert abs(est.value - 0.6) < 0.1 * 0.6
    assert abs(est.value - 0.6) < 2 * est.uncertainty
    assert "1030 stationary frames in 5 windows" in est.evidence


def test_noise_below_the_pixel_grid_is_not_identified():
    with pytest.raises(NotIdentified, match="pixel grid"):
        noise_from_stationary(stationary_windows(0.0, [120, 160], seed=3), "still")


def test_noise_needs_windows_longer_than_the_settling():
    with pytest.raises(IdentifyError, match="settle"):
        noise_from_stationary([np.zeros((5, 2))], "short")


# --- frame lag ----------------------------------------------------------------------------------------------
def step_rich_commands(seed, n_seg=10):
    """Open-loop segments of random heading, length and frequency (stops included), then the same driven back
    (heading + π, reversed), twice: turns, starts, stops and speed changes that keep the robot in view."""
    rng = np.random.default_rng(seed)
    segs = [(rng.uniform(-np.pi, np.pi), int(rng.integers(8, 25)), float(rng.choice([0.0, 6.0, 10.0, 15.0, 25.0])))
            for _ in range(n_seg)]
    segs = [(0.0, 10, 0.0)] + (segs + [(h + np.pi, n, f) for h, n, f in reversed(segs)]) * 2
    b_static = np.concatenate([np.tile(2e-3 * np.array([np.cos(h), np.sin(h)]), (n, 1)) for h, n, _ in segs])
    b_osc = np.concatenate([np.full(n, 1.45e-3 if f > 0 else 0.0) for _, n, f in segs])
    freq = np.concatenate([np.full(n, f) for _, n, f in segs])
    return b_static, b_osc, freq


def rig_log(latency, seed, robot=None, noise_px=0.3):
    """A run log of the simulated rig's sensing chain: robot (step variability on) → camera (lag, noise) →
    Kalman tracker, driven open loop by :func:`step_rich_commands`."""
    b_static, b_osc, freq = step_rich_commands(seed)
    p0 = np.array([2.4e-3, 1.8e-3])
    rob = StickSlipRobot("robot", robot, position=p0, heading=0.0, variability=True)
    cam = Camera(n_spheres=0, latency_frames=latency, position_noise_px=noise_px, primed=(p0, 0.0, NO_SPHERES))
    trk = Tracker(n_spheres=0, position_noise_px=noise_px)
    d = Diagram("rig", [rob, cam, trk],
                [("robot.position", "camera.position"), ("robot.heading", "camera.heading"), *SENSOR_WIRES],
                inputs={"b_static": "robot.b_static_delivered", "b_osc": "robot.b_osc_delivered",
                        "freq": "robot.freq_delivered", "spheres": "camera.spheres"},
                outputs={"robot_est": "tracker.robot_est", "heading_est": "tracker.heading_est",
                         "lost": "tracker.lost"})
    res = simulate(d, len(freq), seed=seed, inputs={"b_static": b_static, "b_osc": b_osc, "freq": freq,
                                                    "spheres": NO_SPHERES})
    assert not res.outputs["lost"].any()
    t = np.arange(len(freq)) / 30.0
    return t, b_static, b_osc, freq, res.outputs["robot_est"][0], res.outputs["heading_est"][0]


@pytest.mark.parametrize("latency", [0, 3, 5])
def test_latency_recovered(latency):
    est = latency_from_commands(*rig_log(latency, seed=11), "synthetic log")
    assert est.name == "camera.toml:camera.latency_frames"
    assert est.value == latency
    assert est.uncertainty == 0.0


def test_latency_not_fooled_by_a_mis_modelled_turning_drag():
    """The rig's robot turns twice as slowly as the model's (film gap 1 µm, not 2 µm) and is 30 % faster: the
    heading time factor and the speed scale absorb both, the lag stays 3."""
    base = load_robot()
    rig = dataclasses.replace(base, film_gap=0.5 * base.film_gap, pitch_drag_ratio=0.5 * base.pitch_drag_ratio,
                              slip_efficiency=1.3 * base.slip_efficiency)
    est = latency_from_commands(*rig_log(3, seed=12, robot=rig, noise_px=1.0), "slow-turning rig")
    assert est.value == 3
    factor = float(re.search(r"heading time factor ([0-9.]+)", est.evidence).group(1))
    assert 1.5 < factor < 2.5


def test_latency_at_the_edge_of_the_search_is_uncertain():
    est = latency_from_commands(*rig_log(6, seed=13), "synthetic log")  # latency_max_frames = 6
    assert est.value == 6 and est.uncertainty == 1.0
    assert "edge of the search" in est.evidence


def test_latency_needs_command_onsets():
    t, b_static, b_osc, freq, est, heading = rig_log(2, seed=14)
    n = len(t)
    with pytest.raises(NotIdentified, match="never change"):
        latency_from_commands(t, np.tile(b_static[0], (n, 1)), np.full(n, 1.45e-3), np.full(n, 10.0), est, heading,
                              "constant drive")


# --- dropped frames -----------------------------------------------------------------------------------------
def test_drop_rate_counts_gaps_in_the_frame_counter():
    rng = np.random.default_rng(0)
    runs, removed = [], 0
    for start, n, k in [(0, 1000, 10), (5000, 2000, 25), (17, 500, 0)]:
        frames = np.arange(start, start + n)
        gone = rng.choice(np.arange(1, n - 1), k, replace=False)  # interior frames: both ends delivered
        runs.append(np.delete(frames, gone))
        removed += k
    est = drop_rate(runs, "3 runs")
    assert est.name == "camera.toml:camera.drop_probability_ratio"
    assert est.value == pytest.approx(removed / 3500)
    nt, pt = 3501, (removed + 0.5) / 3501
    assert est.uncertainty == pytest.approx(np.sqrt(pt * (1 - pt) / nt))
    assert f"{removed} of 3500 frames" in est.evidence


def test_no_drops_still_has_an_upper_uncertainty():
    est = drop_rate([np.arange(3000)], "clean run")
    assert est.value == 0.0
    assert est.uncertainty == pytest.approx(np.sqrt(0.5 / 3001 * (1 - 0.5 / 3001) / 3001))
    assert 0.7 / 3000 < est.uncertainty < 0.72 / 3000


def test_drop_rate_rejects_a_counter_that_goes_back():
    with pytest.raises(IdentifyError, match="do not increase"):
        drop_rate([np.array([1, 2, 3, 2, 4])], "torn")
    with pytest.raises(NotIdentified):
        drop_rate([[]], "empty")
