"""``--conditions paper``: the studies' controllers as the paper ran its own (magctl.studies.conditions)."""

import pytest

from magctl.config import load_model
from magctl.core.errors import MagctlError
from magctl.core.units import UM
from magctl.loops import Experiment, experiment_controller
from magctl.studies.conditions import conditioned


def test_paper_conditions_set_the_papers_servo_models_bounds_and_release():
    front = conditioned(Experiment("front", task={"kc": 1.0, "delta0": 98 * UM}), "paper")
    assert front.task["delta0"] == pytest.approx(127 * UM) and front.task["servo"] == "paper"
    assert conditioned(Experiment("front", task={"kc": 0.0, "delta0": 0.0}), "paper").task["delta0"] == 0.0
    side = conditioned(Experiment("side", task={"model": "lin-fit", "ks": 0.9}), "paper")
    assert side.task["model"] == "lin" and side.task["min_gap"] == pytest.approx(370 * UM)
    assert side.task["clearance"] == pytest.approx(650 * UM)
    assert conditioned(Experiment("side", task={"model": "exp-fit"}), "paper").task["model"] == "exp"
    fixed = conditioned(Experiment("side", task={"fixed_gap": 500 * UM}), "paper")
    assert fixed.task["fixed_gap"] == pytest.approx(500 * UM) and "model" not in fixed.task
    fig15 = conditioned(Experiment("front-side-assembly", task={}), "paper")   # options go to its side stage
    assert fig15.task["min_gap"] == pytest.approx(370 * UM) and fig15.task["servo"] == "paper"
    mine = Experiment("side", task={"model": "lin-fit"})
    assert conditioned(mine, "magctl") is mine
    with pytest.raises(MagctlError, match="conditions 'lab' is not one of magctl, paper"):
        conditioned(mine, "lab")


def test_the_conditioned_controller_is_built_with_them():
    """The diagram the study runs: the task holds the paper's bound and printed model, the servo its setting."""
    exp = conditioned(Experiment("side", task={"model": "exp-fit", "ks": 0.9}), "paper")
    ctrl = experiment_controller(exp)
    task = ctrl.blocks["task"]
    assert task.min_gap == pytest.approx(370 * UM) and task.clearance == pytest.approx(650 * UM)
    assert type(task.model).__name__ == "ExpSideModel" and task.model.rate == pytest.approx(0.009042 / UM)
    default = experiment_controller(Experiment("side", task={"model": "exp-fit", "ks": 0.9}))
    assert default.blocks["task"].min_gap == pytest.approx(load_model("push").side.min_gap)   # the plant's bound
    assert default.blocks["task"].min_gap < 370 * UM
    paper_servo, tuned = ctrl.blocks["servo"], default.blocks["servo"]
    assert paper_servo.ki > 0 and not paper_servo.anti_windup      # models/servo.toml [paper]: the basic PI
    assert tuned.ki == 0.0
