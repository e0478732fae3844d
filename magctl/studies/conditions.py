"""The conditions a reproduction runs under: magctl's own (the default) or the paper's (§VI).

``magctl reproduce --conditions paper`` runs every closed-loop controller of the studies as the paper ran its
own, where the route allows: the paper-like PI servo with its ≈ 100 µm overshoot (``servo = "paper"``,
``models/servo.toml``, §VI-A), the side-push models as printed (eq 22 for ``exp-fit``, eq 23 for ``lin-fit``),
the paper's contact bound (370 µm, §IV-D) and clearance (650 µm, §VI), and the paper's simulated release as
the model δ(0) (127 µm, §IV-D). The plant stays magctl's: the paper's rig is not available, only its
controllers. The default, ``magctl``, runs magctl's controllers with the bounds taken from magctl's plant.
The paper's values are ``models/push.toml [paper_conditions]`` and ``[release] model_um``.
"""

from __future__ import annotations

import dataclasses

from magctl.config import load_model
from magctl.core.errors import MagctlError

CONDITIONS = {"magctl": "magctl's controllers, bounds from magctl's plant (the default)",
              "paper": "the paper's servo, printed eq 22/23, 370 µm bound, 650 µm clearance, δ(0) = 127 µm"}
PAPER_MODELS = {"lin-fit": "lin", "exp-fit": "exp"}
"""magctl's refitted side-push models replaced by the paper's printed eq 23 and eq 22."""


def task_fields(kind: str) -> set[str]:
    """The options the task of an experiment ``kind`` takes (its parameter record's fields)."""
    from magctl.control.push_params import AssemblyParams
    from magctl.loops import EXPERIMENT_TASKS, PUSH_TASKS

    # Fig 15's protocol has no record of its own: its options go to its side-push assembly
    record = getattr(PUSH_TASKS[EXPERIMENT_TASKS[kind]], "PARAMS", AssemblyParams)
    return {f.name for f in dataclasses.fields(record)}


def conditioned(exp, conditions: str):
    """``exp`` (an :class:`~magctl.loops.Experiment`) under ``conditions`` (:data:`CONDITIONS`)."""
    if conditions not in CONDITIONS:
        raise MagctlError(f"conditions {conditions!r} is not one of {', '.join(CONDITIONS)}")
    if conditions == "magctl":
        return exp
    push = load_model("push")
    paper = push.paper_conditions      # models/push.toml [paper_conditions]: §IV-D bound, servo
    names = task_fields(exp.kind)
    task = dict(exp.task)
    if "min_gap" in names:
        task["min_gap"] = float(paper.min_gap)
    if "clearance" in names:
        task["clearance"] = float(push.common.clearance)     # §VI's 650 µm, [common] clearance_um
    task["servo"] = str(paper.servo)
    if isinstance(task.get("model"), str):      # the default model is already the printed eq 23
        task["model"] = PAPER_MODELS.get(task["model"], task["model"])
    if task.get("delta0", 0.0) > 0:
        task["delta0"] = float(push.release.model)         # the paper's simulated D_p,r, 127 µm
    return dataclasses.replace(exp, task=task)

