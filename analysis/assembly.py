"""Figs 3, 9, 15 — assembling two spheres: front pushing fails, side pushing succeeds.

Two 210 µm spheres start 600 µm apart (centre to centre). The front-push variant
pushes sphere 1 into sphere 2 and retracts; the fluid drags sphere 1 back by D_p,r
and the pair separates (Fig 3). The side-push method (§V-C) moves along a motion line
parallel to the adjusted line at θ_n = 30° and repeats until eq 21 holds
(|P_s2 − P_s1| ≤ R₁ + R₂ + ε_as). The plant is the experiment-like one of the
front-push study (D_p,r calibrated to 300 µm, ±10 % mobility scatter, camera noise,
stick-slip variability).
"""

from __future__ import annotations

import numpy as np

from magctl.control.push.common import task_defaults
from magctl.control.status import Status
from magctl.loops import Experiment, Variability, geometry
from magctl.studies.push import controller_summary, run_experiments, trial_path
from magctl.studies.runner import Computed, PaperRow, StudyContext

NAME = "assembly"
TITLE = "Figs 3, 9, 15 — two-sphere assembly: front push vs side push"
ORDER = 53
DEFAULT_TRIALS = 100
PLANT = Variability(calibrated=True, release_scatter=0.1)
EPS_AS_UM = task_defaults("assembly")["eps_as"] / 1e-6  # ε_as of eq 21 (models/push.toml)


def experiments() -> dict[str, Experiment]:
    """Both assemblies with the default controllers (θ_n = 30°, ε_as from ``models/push.toml``)."""
    theta = np.rad2deg(task_defaults("assembly")["theta_n"])
    side = f"side-push assembly (θ_n={theta:.0f}°)"
    return {
        "front-push assembly": Experiment("front-assembly", max_frames=6000, variability=PLANT,
                                          label="front-push assembly"),
        side: Experiment("assembly", max_frames=9000, variability=PLANT, label=side),
    }


def compute(ctx: StudyContext) -> Computed:
    """Run both assembly methods; their final gaps, and trial 0 of each for the GIFs."""
    n = ctx.n_trials(DEFAULT_TRIALS)
    exps = experiments()
    runs, _ = run_experiments(ctx, exps, n)
    summaries = {label: controller_summary(r) for label, r in runs.items()}
    results = {"trials": n, "eps_as_um": EPS_AS_UM, "methods": summaries, "plant": PLANT.describe()}
    data = {"final_gap_um": {label: np.asarray(r["final_error_um"]) for label, r in runs.items()},
            "assembled": {label: np.asarray(r["status"]) == Status.CONVERGED for label, r in runs.items()},
            "front_trial": trial_path(ctx, exps["front-push assembly"]),
            "side_trial": trial_path(ctx, exps["side-push assembly (θ_n=30°)"])}
    return Computed(results, data)


def draw(computed: Computed, ctx: StudyContext) -> list:
    """Histogram of the final gaps (cf. Figs 3, 15) and a GIF of each method."""
    from magctl.studies.figures import animate_trial, pyplot, save_figure

    plt = pyplot()
    d = computed.data
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for label, gaps in d["final_gap_um"].items():
        ax.hist(gaps, bins=30, alpha=0.6, label=f"{label}: {np.mean(d['assembled'][label]):.0%} assembled")
    ax.axvline(EPS_AS_UM, color="k", ls="--", lw=0.8, label=f"ε_as = {EPS_AS_UM:g} µm (eq 21)")
    ax.set_xlabel("final surface gap between the spheres (µm)")
    ax.set_ylabel("trials")
    ax.set_title(f"Two-sphere assembly, {computed.results['trials']} trials each (cf. Figs 3, 15)", fontsize=10)
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    hist = save_figure(fig, ctx.figure_path("assembly_gaps"), dpi=120)
    goal = geometry("assembly")["goal"]
    return [hist, animate_trial(d["front_trial"], ctx.figure_path("assembly_front", ".gif"), goal),
            animate_trial(d["side_trial"], ctx.figure_path("assembly_side", ".gif"), goal)]


def summarise(computed: Computed) -> tuple[list[str], list[PaperRow]]:
    """Share assembled and attempts of each method, against the paper's Figs 3 and 15."""
    r = computed.results
    summaries = r["methods"]
    front, side = summaries["front-push assembly"], summaries["side-push assembly (θ_n=30°)"]
    summary = [f"{r['trials']} trials each; plant: {r['plant']}.", "",
               "| method | assembled (eq 21) | mean attempts | median final gap (µm) |", "|---|---|---|---|"]
    for label, s in summaries.items():
        summary.append(f"| {label} | {s['converged_fraction']:.0%} | {s['mean_attempts_all']:.1f} | "
                       f"{s['final_error_um_median']:.0f} |")
    paper = [
        PaperRow("assembly by front pushing", "fails: spheres separate on retraction (Fig 3, 15d)",
                 f"{front['converged_fraction']:.0%} assembled, median gap {front['final_error_um_median']:.0f} µm"),
        PaperRow("assembly by side pushing, θ_n = 30°", "succeeds (after two side pushes, Fig 15f)",
                 f"{side['converged_fraction']:.0%} assembled, {side['mean_attempts_all']:.1f} mean attempts"),
    ]
    return summary, paper
