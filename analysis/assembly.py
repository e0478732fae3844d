"""Figs 3, 9, 15 — assembling two spheres: front pushing fails, side pushing succeeds.

Two 210 µm spheres start 600 µm apart (centre to centre). The front-push variant
pushes sphere 1 into sphere 2 and retracts; the fluid drags sphere 1 back by D_p,r
and the pair separates (Fig 3). The side-push method (§V-C) moves along a motion line
parallel to the adjusted line at θ_n = 30° and repeats until eq 21 holds
(|P_s2 − P_s1| ≤ R₁ + R₂ + ε_as). The paper's experiment (Fig 15) chains the two: one
front push, the pair separates on retraction, then side passes close it. The side passes use
the §VI-B controller with its model fitted to magctl's Fig 6 curve (lin-fit, K_s = 0.9, as in
the side-push study). The plant is the experiment-like one of the front-push study (D_p,r
calibrated to 300 µm, ±10 % mobility scatter, camera noise, stick-slip variability).
"""

from __future__ import annotations

import numpy as np

from magctl.control.push_params import task_defaults
from magctl.control.status import Status
from magctl.loops import Experiment, Variability, geometry
from magctl.studies.paper_statistics import p_all, p_none
from magctl.studies.push import controller_summary, run_experiments, trial_path
from magctl.studies.runner import Cause, Computed, PaperRow, StudyContext, claim

NAME = "assembly"
TITLE = "Figs 3, 9, 15 — two-sphere assembly: front push vs side push"
ORDER = 53
DEFAULT_TRIALS = 100
PLANT = Variability(release_scatter=0.1)
EPS_AS_UM = task_defaults("assembly")["eps_as"] / 1e-6  # ε_as of eq 21 (models/push.toml)
THETA_DEG = np.rad2deg(task_defaults("assembly")["theta_n"])
SIDE_TASK = {"model": "lin-fit"}
FRONT = "front-push assembly"
SIDE = f"side-push assembly (θ_n={THETA_DEG:.0f}°)"
FIG15 = "front push, then side passes (Fig 15)"


def experiments() -> dict[str, Experiment]:
    """Both assemblies with the default controllers (θ_n = 30°, ε_as from ``models/push.toml``)."""
    return {
        FRONT: Experiment("front-assembly", max_frames=6000, variability=PLANT, label=FRONT),
        SIDE: Experiment("assembly", task=dict(SIDE_TASK), max_frames=9000, variability=PLANT, label=SIDE),
        FIG15: Experiment("front-side-assembly", task=dict(SIDE_TASK), max_frames=9000, variability=PLANT,
                          label=FIG15),
    }


def compute(ctx: StudyContext) -> Computed:
    """Run the three assembly methods; their final gaps, and trial 0 of each for the GIFs."""
    n = ctx.n_trials(DEFAULT_TRIALS)
    exps = experiments()
    runs, _ = run_experiments(ctx, exps, n)
    summaries = {label: controller_summary(r) for label, r in runs.items()}
    results = {"trials": n, "eps_as_um": EPS_AS_UM, "methods": summaries, "plant": PLANT.describe()}
    data = {"final_gap_um": {label: np.asarray(r["final_error_um"]) for label, r in runs.items()},
            "assembled": {label: np.asarray(r["status"]) == Status.CONVERGED for label, r in runs.items()},
            "front_trial": trial_path(ctx, exps[FRONT]),
            "side_trial": trial_path(ctx, exps[SIDE]),
            "fig15_trial": trial_path(ctx, exps[FIG15])}
    fig15 = runs[FIG15]
    side_passes = np.asarray(fig15["attempts"]) - 1
    results["fig15_side_passes_median"] = float(np.median(side_passes[data["assembled"][FIG15]])) \
        if data["assembled"][FIG15].any() else None
    results["fig15_gap_after_front_push_um_median"] = float(np.nanmedian(np.asarray(fig15["error_um"])[:, 1]))
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
            animate_trial(d["side_trial"], ctx.figure_path("assembly_side", ".gif"), goal),
            animate_trial(d["fig15_trial"], ctx.figure_path("assembly_fig15", ".gif"), goal)]


def summarise(computed: Computed) -> tuple[list[str], list[PaperRow]]:
    """Share assembled and attempts of each method, against the paper's Figs 3 and 15."""
    r = computed.results
    summaries = r["methods"]
    front, side = summaries[FRONT], summaries[SIDE]
    summary = [f"{r['trials']} trials each; plant: {r['plant']}.", "",
               "| method | assembled (eq 21) | mean attempts | median final gap (µm) |", "|---|---|---|---|"]
    for label, s in summaries.items():
        summary.append(f"| {label} | {s['converged_fraction']:.0%} | {s['mean_attempts_all']:.1f} | "
                       f"{s['final_error_um_median']:.0f} |")
    fig15 = summaries[FIG15]
    passes, gap1 = r["fig15_side_passes_median"], r["fig15_gap_after_front_push_um_median"]
    summary += ["", f"Fig 15 protocol: after the front push the spheres are {gap1:.0f} µm apart (median surface "
                f"gap); the side passes then take {passes if passes is None else f'{passes:.0f}'} passes (median of "
                "the assembled trials; the paper's Fig 15 shows two)."]
    median_passes = "no" if passes is None else f"{passes:.0f}"
    sec, loop = "§VI-C", "closed loop"
    paper = [
        claim(sec, "front pushing does not assemble: the spheres separate as the robot retracts",
              "fails (Figs 3, 15c–d)",
              f"{front['converged_fraction']:.0%} assembled, median gap {front['final_error_um_median']:.0f} µm",
              loop, holds=front["converged_fraction"] < 0.1, p_paper=p_none(front["converged_fraction"], n=1),
              cause=Cause(f"the paper shows one trial, and {1 - front['converged_fraction']:.0%} of magctl's "
                          "front-push trials end with the pair apart, so one such trial is not unlikely.",
                          1 - front["converged_fraction"] >= 0.05)),
        claim(sec, f"side pushing assembles (θ_n = {THETA_DEG:.0f}°)", "succeeds",
              f"{side['converged_fraction']:.0%} assembled, {side['mean_attempts_all']:.1f} mean passes",
              loop, holds=side["converged_fraction"] >= 0.9, p_paper=p_all(side["converged_fraction"], n=1),
              cause=Cause(f"{1 - side['converged_fraction']:.0%} of the side-push trials end unassembled.",
                          side["converged_fraction"] < 0.9)),
        claim(sec, "Fig 15: a front push, then side passes assemble the pair (two passes in the paper's run)",
              "assembled after two side passes",
              f"{fig15['converged_fraction']:.0%} assembled; median {passes if passes is None else f'{passes:.0f}'} "
              f"side passes from a {gap1:.0f} µm gap", loop,
              holds=fig15["converged_fraction"] >= 0.9 and passes is not None and passes <= 3,
              cause=(Cause(f"{1 - fig15['converged_fraction']:.0%} of the trials end unassembled.", True)
                     if fig15["converged_fraction"] < 0.9 else
                     Cause(f"the front push leaves a {gap1:.0f} µm gap, which the side passes close in a median of "
                           f"{median_passes} passes, not the paper's two.", passes is not None and passes > 3))),
    ]
    return summary, paper
