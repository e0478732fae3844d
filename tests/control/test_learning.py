"""Learning-law blocks (eq 13, eq 18): behaviour, python-control export, errors."""

import control
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magctl.control.learning import LearningLaw, front_push_law, side_push_law
from magctl.core.errors import MagctlError


@settings(max_examples=30, deadline=None)
@given(st.floats(-3, 3), st.floats(-1e-3, 1e-3))
def test_front_law_is_the_integrator_of_eq_13(kc, delta0):
    law = front_push_law(kc, delta0)
    tf = control.tf(law.to_control())
    ref = control.tf([kc], [1, -1], dt=1)  # eq 14, written from the paper
    assert tf.dt == 1
    w = np.exp(1j * np.array([0.3, 1.1, 2.5]))
    np.testing.assert_allclose(tf(w), ref(w), atol=1e-12)
    # stepping: δ(i+1) = δ(i) + K_c e(i)
    s = law.initial_state(1)
    y0 = law.output(s, {})["y"].copy()
    s = law.update(s, {"e": np.array([2e-4])})
    assert y0[0] == pytest.approx(delta0)
    assert law.output(s, {})["y"][0] == pytest.approx(delta0 + kc * 2e-4)


def test_side_law_sign_and_printed_variant():
    e = np.array([1e-5])  # D_s,act − D_s,des: an over-push
    fixed = side_push_law(0.9)
    printed = side_push_law(0.9, printed_sign=True)
    s1 = fixed.update(fixed.initial_state(1), {"e": e})
    s2 = printed.update(printed.initial_state(1), {"e": e})
    # after an over-push the corrected law asks for less displacement next time
    assert s1["x"][0] == pytest.approx(-0.9e-5)
    assert s2["x"][0] == pytest.approx(+0.9e-5)


def test_update_where_and_output_not_mutated():
    law = LearningLaw("l", 0.5, initial=[0.0, 1.0, 2.0])
    s = law.initial_state(3)
    y = law.output(s, {})["y"]
    keep = y.copy()
    s = law.update_where(s, {"e": np.array([1.0, 1.0, 1.0])}, np.array([True, False, True]))
    np.testing.assert_array_equal(y, keep)
    np.testing.assert_allclose(law.output(s, {})["y"], [0.5, 1.0, 2.5])


def test_per_trial_gains_batch_and_no_transfer_function():
    law = LearningLaw("l", [0.0, 1.0])
    s = law.update(law.initial_state(2), {"e": np.array([1.0, 1.0])})
    np.testing.assert_allclose(s["x"], [0.0, 1.0])
    with pytest.raises(MagctlError, match="per-trial gains"):
        law.to_control()
    with pytest.raises(MagctlError, match="batch of 3"):
        law.initial_state(3)


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), "abc"])
def test_bad_gains_are_named(bad):
    with pytest.raises(MagctlError, match="K_c"):
        front_push_law(bad)
    with pytest.raises(MagctlError, match="K_s"):
        side_push_law(bad)


def test_bad_initial_value():
    with pytest.raises(MagctlError, match="initial value"):
        front_push_law(1.0, float("nan"))
