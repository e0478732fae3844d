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

from magctl.control.push.common import CONVERGED
from magctl.loops import Experiment, Variability, geometry
from magctl.studies.push import animate_one, run_experiments, summarise
from magctl.studies.runner import PaperRow, StudyContext, StudyResult

NAME = "assembly"
TITLE = "Figs 3, 9, 15 — two-sphere assembly: front push vs side push"
ORDER = 53
DEFAULT_TRIALS = 100
PLANT = Variability(calibrated=True, release_scatter=0.1)
EPS_AS_UM = 10.0


def experiments() -> dict[str, Experiment]:
    common = dict(eps_as=EPS_AS_UM * 1e-6)
    return {
        "front-push assembly": Experiment("front-assembly", task=dict(common), max_frames=6000, variability=PLANT,
                                          label="front-push assembly"),
        "side-push assembly (θ_n=30°)": Experiment("assembly", task=dict(common, theta_n=np.deg2rad(30.0)),
                                                   max_frames=9000, variability=PLANT,
                                                   label="side-push assembly (θ_n=30°)"),
    }


def run(ctx: StudyContext) -> StudyResult:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = ctx.n_trials(DEFAULT_TRIALS)
    exps = experiments()
    results = run_experiments(ctx, exps, n)
    summaries = {label: summarise(r) for label, r in results.items()}
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for label, r in results.items():
        gaps = np.asarray(r["final_error_um"])
        ax.hist(gaps, bins=30, alpha=0.6, label=f"{label}: {np.mean(r['status'] == CONVERGED):.0%} assembled")
    ax.axvline(EPS_AS_UM, color="k", ls="--", lw=0.8, label=f"ε_as = {EPS_AS_UM:g} µm (eq 21)")
    ax.set_xlabel("final surface gap between the spheres (µm)")
    ax.set_ylabel("trials")
    ax.set_title(f"Two-sphere assembly, {n} trials each (cf. Figs 3, 15)", fontsize=10)
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    hist = ctx.figure_path("assembly_gaps")
    fig.savefig(hist, dpi=120)
    plt.close(fig)
    goal = geometry("assembly")["goal"]
    figs = [hist,
            animate_one(exps["front-push assembly"], ctx.figure_path("assembly_front", ".gif"), ctx.seed, goal),
            animate_one(exps["side-push assembly (θ_n=30°)"], ctx.figure_path("assembly_side", ".gif"), ctx.seed,
                        goal)]
    front, side = summaries["front-push assembly"], summaries["side-push assembly (θ_n=30°)"]
    summary = [f"{n} trials each; plant: {PLANT.describe()}.", "",
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
    return StudyResult(NAME, {"trials": n, "eps_as_um": EPS_AS_UM, "methods": summaries, "plant": PLANT.describe()},
                       figs, summary, paper)
