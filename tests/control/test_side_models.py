"""The side-push models F of eq 17: eq 22/23 as printed and the same forms fitted to magctl's Fig 6."""

import numpy as np
import pytest

from magctl.config import load_model
from magctl.control.side_models import SIDE_MODELS, ExpSideModel, LinSideModel, side_model
from magctl.core.errors import MagctlError
from magctl.core.units import UM


@pytest.mark.parametrize("gap_um", [400.0, 500.0, 600.0])
def test_linearised_is_the_tangent_of_f(gap_um):
    exp = ExpSideModel()
    lin = exp.linearised(gap_um * UM)
    ds0 = float(exp.displacement(gap_um * UM))
    h = 1e-4 * ds0
    numeric = (exp.gap(ds0 + h) - exp.gap(ds0 - h)) / (2 * h)  # central difference of F
    assert lin.gap(ds0) == pytest.approx(gap_um * UM, rel=1e-12)
    assert lin.slope_ == pytest.approx(float(numeric), rel=1e-6)


def test_the_papers_eq_23_is_not_the_tangent_at_500_um():
    # tangent of eq 22 at D_g = 500 µm, worked by hand: D_s0 = 1755·e^(−4.521) µm, slope −1/(0.009042·D_s0)
    ds0 = 1755 * np.exp(-0.009042 * 500)
    lin = ExpSideModel().linearised(500 * UM)
    assert lin.slope_ == pytest.approx(-1 / (0.009042 * ds0), rel=1e-9)
    assert lin.intercept / UM == pytest.approx(500 + 1 / 0.009042, rel=1e-9)
    assert abs(lin.slope_ - LinSideModel().slope_) > 0.4  # −5.79 against the printed −5.29


def test_fitted_models_come_from_push_toml():
    fit = load_model("push").side_fit
    exp, lin = side_model("exp-fit"), side_model("lin-fit")
    assert exp.amplitude == pytest.approx(fit.amplitude) and exp.rate == pytest.approx(fit.rate)
    ds0 = float(exp.displacement(fit.about_gap))
    assert lin.gap(ds0) == pytest.approx(fit.about_gap, rel=1e-12)          # touches F there …
    assert lin.slope_ == pytest.approx(-1 / (fit.rate * ds0), rel=1e-12)   # … with F's slope
    assert exp.name == "exp-fit" and lin.name == "lin-fit"


def test_the_papers_models_are_push_toml_paper_side_bit_for_bit(tmp_path, monkeypatch):
    """Eq 22/23 as printed are models/push.toml [paper_side] (with their sources), read as the very doubles the
    constants were (1755 * UM, 0.009042 / UM, −5.29, 621 * UM); a changed file changes the models."""
    assert (ExpSideModel().amplitude, ExpSideModel().rate) == (1755 * UM, 0.009042 / UM)
    assert (LinSideModel().slope_, LinSideModel().intercept) == (-5.29, 621 * UM)
    assert side_model("exp") == ExpSideModel() and side_model("lin") == LinSideModel()
    sources = load_model("push").paper_side.sources
    assert all(sources[k].startswith("paper eq 2") for k in ("amplitude", "rate", "slope", "intercept"))
    from magctl.config import models_dir

    text = (models_dir() / "push.toml").read_text(encoding="utf-8")
    changed = text.replace("amplitude_um = { value = 1755.0,", "amplitude_um = { value = 1000.0,")
    assert changed != text
    (tmp_path / "push.toml").write_text(changed, encoding="utf-8")
    monkeypatch.setenv("MAGCTL_MODELS", str(tmp_path))
    assert side_model("exp").amplitude == 1000 * UM and side_model("exp-fit").amplitude != 1000 * UM


def test_unknown_model_lists_the_known_ones():
    with pytest.raises(MagctlError) as err:
        side_model("cubic")
    assert all(name in str(err.value) for name in SIDE_MODELS)


def test_rig_options_take_every_side_model_and_the_fig15_task():
    from magctl.rig.tasks import TaskError, resolve_options, task_options

    assert resolve_options("side-push", {"model": "lin-fit"})["model"] == "lin-fit"
    opts = resolve_options("front-side-assemble", {"front_attempts": 2, "model": "exp-fit", "theta_n_deg": 20})
    assert opts["front_attempts"] == 2 and opts["theta_n"] == pytest.approx(np.deg2rad(20))
    assert "front_attempts" in task_options("front-side-assemble")
    with pytest.raises(TaskError, match="exp-fit"):
        resolve_options("assemble", {"model": "cubic"})
    assert resolve_options("side-push", {"learning": "curve"})["learning"] == "curve"
    with pytest.raises(TaskError, match="learning='online' is not one of eq18, curve"):
        resolve_options("assemble", {"learning": "online"})
    assert resolve_options("side-push", {"dirt_response": "front"})["dirt_response"] == "front"
    assert resolve_options("front-push", {"learning": "release"})["learning"] == "release"
    with pytest.raises(TaskError, match="learning='curve' is not one of eq13, release"):
        resolve_options("front-push", {"learning": "curve"})
    with pytest.raises(TaskError, match="dirt_response='wash' is not one of none, front"):
        resolve_options("side-push", {"dirt_response": "wash"})
