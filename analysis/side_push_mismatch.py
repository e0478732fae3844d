"""Side pushing with the paper's own eq 22/23 on magctl's plant: the model-mismatch study.

The paper's eq 22 (and its linearisation eq 23) were fitted to the paper's Fig 6 simulation.
magctl's Fig 6 curve decays more slowly (``sidepush-curve``), so the printed models are a
mismatched model of this plant: at a given gap they predict a different displacement. This
study runs the paper's exponential model without learning and its best controller (eq 23 with
K_s = 0.9) on the plant and seeds of the Fig 12 reproduction (``side-push``), beside the same
controllers with the forms refitted to magctl's curve, and reads the difference through the
local slope ratio ρ = F_lin′/F_act′ that the iteration-domain analysis uses (eq 19–20).
"""

from __future__ import annotations

import numpy as np

from magctl.control.side_models import side_model
from magctl.studies import runner as studies
from magctl.studies.push import controller_summary, controller_table, overshoot_fraction, reuse_note, run_experiments
from magctl.studies.runner import Computed, PaperRow, StudyContext

NAME = "side-push-mismatch"
TITLE = "Side pushing with the paper's eq 22/23 on magctl's plant (model mismatch)"
ORDER = 54
DEFAULT_TRIALS = 100
REUSES = ("side-push",)

PAIRS = {"exp, K_s=0": ("exp", 0.0, "exp-fit, K_s=0"), "lin, K_s=0.9": ("lin", 0.9, "lin-fit, K_s=0.9")}
"""Paper-model controller → (model, K_s, the refitted controller of the Fig 12 reproduction)."""


def slope_ratio(model: str, gaps_m: np.ndarray) -> np.ndarray:
    """ρ = F′_model / F′_plant at the plant's displacement for each gap, the plant being magctl's fit."""
    plant = side_model("exp-fit")
    ds = plant.displacement(gaps_m)
    return np.asarray(side_model(model).slope(ds) / plant.slope(ds), dtype=float)


def compute(ctx: StudyContext) -> Computed:
    """The paper-model controllers and their refitted twins, same plant and seeds."""
    side = studies.get("side-push")
    n = ctx.n_trials(DEFAULT_TRIALS)
    exps = {}
    for label, (model, ks, twin) in PAIRS.items():
        exps[label] = side.side_experiment(label, dict(model=model, ks=ks))
        exps[twin] = side.experiments()[twin]
    runs, sources = run_experiments(ctx, exps, n)
    summaries = {label: controller_summary(r) for label, r in runs.items()}
    for label, r in runs.items():
        summaries[label]["overshoot_fraction"] = overshoot_fraction(r, side.EPS_UM)
    gaps = np.array([370.0, 500.0, 650.0]) * 1e-6
    plant = side_model("exp-fit")
    results = {
        "trials_per_controller": n, "controllers": summaries, "plant": side.PLANT.describe(),
        "pairs": {k: v[2] for k, v in PAIRS.items()}, "trials_from_study": sources,
        "gaps_um": (gaps * 1e6).tolist(),
        "plant_displacement_um": (plant.displacement(gaps) * 1e6).tolist(),
        "eq22_displacement_um": (side_model("exp").displacement(gaps) * 1e6).tolist(),
        "rho_lin": slope_ratio("lin", gaps).tolist(), "rho_lin_fit": slope_ratio("lin-fit", gaps).tolist(),
    }
    return Computed(results, {"max_attempts": side.MAX_ATTEMPTS})


def draw(computed: Computed, ctx: StudyContext) -> list:
    """Converged share versus attempts, each paper-model controller beside its refitted twin."""
    from magctl.studies.figures import plot_convergence

    r = computed.results
    return [plot_convergence(r["controllers"], ctx.figure_path("side_push_mismatch"),
                             f"Side pushing: paper's eq 22/23 vs refitted, {r['trials_per_controller']} trials",
                             computed.data["max_attempts"])]


def summarise(computed: Computed) -> tuple[list[str], list[PaperRow]]:
    """The mismatch in numbers, the controllers side by side, and one row per pair."""
    r = computed.results
    s = r["controllers"]
    g, plant, eq22 = r["gaps_um"], r["plant_displacement_um"], r["eq22_displacement_um"]
    summary = [
        f"{r['trials_per_controller']} trials per controller; plant: {r['plant']} (the Fig 12 reproduction's).",
        "Per pass at D_g = " + " / ".join(f"{x:.0f}" for x in g) + " µm, magctl's plant moves the sphere "
        + " / ".join(f"{x:.1f}" for x in plant) + " µm; eq 22 predicts " + " / ".join(f"{x:.1f}" for x in eq22)
        + " µm.",
        "Local slope ratio ρ = F_lin′/F_act′ (1 = a perfect model; eq 20 needs K_s·ρ < 2) at those gaps: eq 23 "
        + " / ".join(f"{x:.2f}" for x in r["rho_lin"]) + ", lin-fit " + " / ".join(f"{x:.2f}" for x in r["rho_lin_fit"])
        + ".",
        "",
        *controller_table(s, computed.data["max_attempts"], ("pushed past the goal", "overshoot_fraction")),
        "", reuse_note(r["trials_from_study"], NAME),
    ]
    paper = [PaperRow(f"side push, paper's {label} on magctl's plant (model mismatch)",
                      f"{twin} (refitted): {s[twin]['mean_attempts_all']:.1f} mean attempts, "
                      f"{s[twin]['converged_fraction']:.0%} converged",
                      f"{s[label]['mean_attempts_all']:.1f} mean attempts, "
                      f"{s[label]['converged_fraction']:.0%} converged",
                      note="the paper column is magctl's refitted controller on the same trials", model="closed loop")
             for label, twin in r["pairs"].items()]
    return summary, paper
