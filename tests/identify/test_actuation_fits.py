"""Speed-curve identification: the stick-slip model's steady speed fitted back to segments made from it."""

import dataclasses

import numpy as np
import pytest

from magctl.identify.actuation import speed_curve, steady_segment_speed
from magctl.identify.estimate import IdentifyError, NotIdentified
from magctl.plant._stickslip import load_robot
from magctl.plant.robot import steady_speed

BASE = load_robot()
TRUE = dataclasses.replace(BASE, slip_efficiency=1.2 * BASE.slip_efficiency, break_angle=np.deg2rad(6.0))
TRUTH = {"slip_efficiency_1": TRUE.slip_efficiency, "break_angle_deg": 6.0,
         "pitch_drag_ratio_1": TRUE.pitch_drag_ratio}
B_XY = 2e-3


def segments(freqs, amps, seed, noise=0.02):
    """Segments over the grid ``freqs × amps`` (Hz, T) at ``|B_xy|`` = 2 mT: the true model's speed with
    ``noise`` relative scatter, 20–40 frames each."""
    F, A = (g.ravel() for g in np.meshgrid(np.asarray(freqs, float), np.asarray(amps, float)))
    rng = np.random.default_rng(seed)
    v = steady_speed(TRUE, B_XY, A, F) * (1 + noise * rng.standard_normal(F.size))
    b_xy = np.tile([B_XY, 0.0], (F.size, 1))
    return b_xy, A, F, v, rng.integers(20, 41, F.size)


def test_speed_curve_recovers_all_three():
    fit = speed_curve(*segments(np.geomspace(10, 150, 8), np.linspace(0.8e-3, 2.5e-3, 6), seed=0), "grid")
    assert fit.not_identified == {}
    assert [e.key for e in fit.estimates] == list(TRUTH)
    for e in fit.estimates:
        assert e.file == "robot.toml" and e.table == "robot"
        truth = TRUTH[e.key]
        assert abs(e.value - truth) < 0.05 * truth, e
        assert abs(e.value - truth) < 2 * e.uncertainty, e
        assert e.uncertainty < 0.05 * truth


def test_single_frequency_identifies_slip_efficiency_only():
    fit = speed_curve(*segments([20.0], [0.8e-3, 1.2e-3, 1.8e-3, 2.5e-3], seed=1), "one frequency")
    assert [e.key for e in fit.estimates] == ["slip_efficiency_1"]
    eta = fit.estimates[0]
    assert abs(eta.value / TRUTH["slip_efficiency_1"] - 1) < 0.05
    assert 0 < eta.uncertainty < 0.05 * eta.value
    assert "held at the model's values" in eta.evidence
    assert set(fit.not_identified) == {"robot.toml:robot.break_angle_deg", "robot.toml:robot.pitch_drag_ratio_1"}
    assert all("do not span" in why for why in fit.not_identified.values())


def test_speed_curve_needs_segments_that_move():
    with pytest.raises(NotIdentified, match="threshold"):
        speed_curve(np.full(3, B_XY), np.full(3, 0.05e-3), np.full(3, 20.0), np.zeros(3), np.full(3, 30), "stuck")


def test_steady_segment_speed_skips_the_transient():
    rng = np.random.default_rng(2)
    t = np.arange(36) / 30.0
    v = np.array([3e-4, -4e-4])  # 0.5 mm/s
    p = 1e-3 + np.outer(t, v) + rng.normal(0, 2e-6, (36, 2))
    p[:10] = p[10] - np.outer(t[10] - t[:10], 0.3 * v)  # a slow start the line must not see
    seg = steady_segment_speed(t, p, skip_frames=10)
    assert seg.frames == 26
    assert abs(seg.speed - 5e-4) < 3 * seg.uncertainty
    assert seg.uncertainty < 0.02 * 5e-4
    assert steady_segment_speed(t, p).frames == 26  # steady_skip_frames = 10 by default
    with pytest.raises(IdentifyError, match="need ≥ 3"):
        steady_segment_speed(t[:12], p[:12], skip_frames=10)
