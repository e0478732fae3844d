"""Servo-loop analysis against python-control built independently, and against the simulated loop."""

import json

import control
import numpy as np
import pytest

from magctl.cli import main
from magctl.control.servo import Servo, default_servo_setting
from magctl.stability.servo import ServoAnalysisError, analyse, closed_loop, linear_step, step_report

T = 1.0 / 30.0


def _independent(kp, ki, d):
    z = control.tf([1.0, 0.0], [1.0], T)
    C = kp + ki * T / (z - 1)
    P = T / (z - 1)
    D = 1 / z**d if d else control.tf([1.0], [1.0], T)
    return C * P, control.feedback(C * P, D), C * P * D


@pytest.mark.parametrize("kp, ki, d", [(3.5, 2.0, 2), (3.0, 0.0, 2), (6.0, 4.0, 3), (2.0, 1.0, 1), (8.0, 0.0, 4)])
def test_poles_and_margins_agree_with_python_control(kp, ki, d):
    _, cl, loop = _independent(kp, ki, d)
    rep = analyse(kp, ki, d)
    expect = np.sort_complex(control.minreal(cl, verbose=False).poles())
    got = np.sort_complex(rep.poles)
    assert len(got) == len(expect)
    np.testing.assert_allclose(got, expect, atol=1e-6)
    gm, pm, _, _ = control.margin(loop)
    assert rep.gain_margin == pytest.approx(gm, rel=1e-6)
    assert rep.phase_margin_deg == pytest.approx(pm, rel=1e-4)
    assert rep.stable == bool(np.all(np.abs(expect) < 1))


def test_closed_loop_dc_gain_is_one():
    assert control.dcgain(closed_loop(3.5, 2.0, 2)) == pytest.approx(1.0)


def test_p_loop_stability_limit():
    """P-only loop without lag: x[k+1] = (1 − Kp T) x[k] + Kp T r is stable for 0 < Kp T < 2."""
    assert analyse(59.0, 0.0, 0).stable and not analyse(61.0, 0.0, 0).stable
    assert analyse(59.0, 0.0, 0).poles[0].real == pytest.approx(1 - 59.0 * T)


def test_overshoot_and_settling_from_step_response():
    _, cl, _ = _independent(3.5, 2.0, 2)
    t = np.arange(600) * T
    y = np.squeeze(control.step_response(cl, T=t).outputs)
    rep = analyse(3.5, 2.0, 2)
    assert rep.overshoot_ratio == pytest.approx(y.max() - 1.0, rel=1e-6)
    assert analyse(3.0, 0.0, 2).overshoot_ratio == 0.0


@pytest.mark.parametrize("kp, ki", [(3.5, 2.0), (3.0, 0.0), (6.0, 4.0)])
def test_simulated_small_step_matches_linear_model(kp, ki):
    """Below v_max/Kp nothing saturates; with a 0.1 µm pixel the block loop is the linear loop."""
    sv = Servo("servo", kp=kp, ki=ki, speed_max=400e-6, arrive_tol=0.0, anti_windup=True)
    step = 0.5 * 400e-6 / (kp * 2)
    sim = step_report(sv, delay_frames=2, step=step, steps=150, pixel_size=1e-7, start=(10e-6, 10e-6))
    np.testing.assert_allclose(sim["sim_um"], sim["linear_um"], atol=0.1)
    t, x = linear_step(kp, ki, 2, step, 150)
    assert sim["linear_overshoot_um"] == pytest.approx(analyse(kp, ki, 2).overshoot_ratio * step * 1e6, abs=1e-3)


@pytest.mark.parametrize("args, word", [((-1.0, 0.0, 2), "kp"), ((1.0, -1.0, 2), "ki"), ((1.0, 0.0, -1), "delay"),
                                        ((1.0, 0.0, 1.5), "delay")])
def test_bad_arguments(args, word):
    with pytest.raises(ServoAnalysisError, match=word):
        analyse(*args)


def test_cli_json(capsys):
    assert main(["stability", "servo", "--setting", "paper", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["stable"] and doc["delay_frames"] == 2
    assert 80 < doc["sim_overshoot_um"] < 120  # paper §VI-A: ~100 µm
    assert main(["stability", "servo", "--json"]) == 0  # the default setting every controller uses
    doc = json.loads(capsys.readouterr().out)
    assert doc["setting"] == default_servo_setting() == "tuned"
    assert doc["sim_overshoot_um"] < 7.5 and doc["overshoot_percent"] == 0.0


def test_cli_errors(capsys):
    assert main(["stability", "servo", "--kp", "-2"]) == 2
    assert "kp" in capsys.readouterr().err
    assert main(["stability", "servo", "--step-um", "0"]) == 2
