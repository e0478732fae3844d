"""Figs 12–13 — side pushing with the eq 17–18 learning controller, in closed loop.

Six controllers push a 210 µm sphere to a goal 300 µm away without contact (§VI-B):
fixed gaps D_g = 370 µm and 500 µm (the naïve controllers), the exponential (eq 22)
and linear (eq 23) models without learning (K_s = 0), and the linear model with
learning K_s = 0.5 and 0.9; ε_p = 7.5 µm (one pixel), at most 30 attempts,
repositioning round the sphere, 1 mm clear of it (``models/push.toml``, docs/closed-loop.md), to a start 1 mm
behind it; every other setting is the default controller the rig runs too. The plant is the
fluid model itself (uncalibrated, ε = 25 nm), so the controllers' eq 22/23 — fitted
to the paper's COMSOL curve — are a mismatched model of it, as in the paper; camera
noise, stick-slip step variability, a ±10 % per-trial scatter of the sphere's
mobility and a 10 % chance of a sticky patch (§VI-B) make trials differ.
"""

from __future__ import annotations

from magctl.control.push.common import task_defaults
from magctl.loops import Experiment, Variability, geometry
from magctl.studies.push import (
    controller_summary,
    controller_table,
    overshoot_fraction,
    run_experiments,
    trial_path,
)
from magctl.studies.runner import Computed, PaperRow, StudyContext

NAME = "side-push"
TITLE = "Figs 12–13 — side pushing: fixed gaps, models and learning in closed loop"
ORDER = 51
DEFAULT_TRIALS = 100
_DEFAULTS = task_defaults("side")
EPS_UM = _DEFAULTS["eps"] / 1e-6  # one pixel (models/push.toml)
MAX_ATTEMPTS = _DEFAULTS["max_attempts"]
UM = 1e-6
PLANT = Variability(release_scatter=0.1, sticky_probability=0.1)

CONTROLLERS = {
    "D_g=370 µm fixed": dict(fixed_gap=370 * UM, ks=0.0),
    "D_g=500 µm fixed": dict(fixed_gap=500 * UM, ks=0.0),
    "exp, K_s=0": dict(model="exp", ks=0.0),
    "lin, K_s=0": dict(model="lin", ks=0.0),
    "lin, K_s=0.5": dict(model="lin", ks=0.5),
    "lin, K_s=0.9": dict(model="lin", ks=0.9),
}


def experiments() -> dict[str, Experiment]:
    return {label: Experiment("side", task=dict(kw), max_frames=14000, variability=PLANT, label=label)
            for label, kw in CONTROLLERS.items()}


def compute(ctx: StudyContext) -> Computed:
    """Run the six controllers and reduce their trials; trial 0 of lin, K_s=0.9 kept for the GIF."""
    n = ctx.n_trials(DEFAULT_TRIALS)
    exps = experiments()
    runs, _ = run_experiments(ctx, exps, n)
    summaries = {label: controller_summary(r) for label, r in runs.items()}
    for label, r in runs.items():
        summaries[label]["overshoot_fraction"] = overshoot_fraction(r, EPS_UM)
    results = {"trials_per_controller": n, "epsilon_um": EPS_UM, "controllers": summaries,
               "plant": PLANT.describe()}
    return Computed(results, {"runs": runs, "animated": trial_path(ctx, exps["lin, K_s=0.9"])})


def draw(computed: Computed, ctx: StudyContext) -> list:
    """Fig 12 (converged vs attempts), Fig 13 (error vs attempt) and a GIF of one push."""
    from magctl.studies.figures import animate_trial, plot_convergence, plot_errors

    r, runs = computed.results, computed.data["runs"]
    n = r["trials_per_controller"]
    return [
        plot_convergence(r["controllers"], ctx.figure_path("side_push_convergence"),
                         f"Side pushing, {n} trials per controller (cf. Fig 12)", MAX_ATTEMPTS),
        plot_errors({k: runs[k] for k in ("D_g=370 µm fixed", "D_g=500 µm fixed", "lin, K_s=0", "lin, K_s=0.9")},
                    ctx.figure_path("side_push_errors"), "Side pushing error (cf. Fig 13)", EPS_UM, log=True),
        animate_trial(computed.data["animated"], ctx.figure_path("side_push", ".gif"), geometry("side")["goal"]),
    ]


def summarise(computed: Computed) -> tuple[list[str], list[PaperRow]]:
    """The controller table and the paper's side-push claims beside ours."""
    r = computed.results
    summaries, n = r["controllers"], r["trials_per_controller"]
    summary = [
        f"{n} trials per controller; plant: {r['plant']}.",
        "",
        *controller_table(summaries, MAX_ATTEMPTS, ("pushed past the goal", "overshoot_fraction")),
    ]
    s370, s500, best = summaries["D_g=370 µm fixed"], summaries["D_g=500 µm fixed"], summaries["lin, K_s=0.9"]
    paper = [
        PaperRow("side push: D_g=370 µm fixed", "oscillates, fails in many cases",
                 f"{s370['converged_fraction']:.0%} converged, {s370['overshoot_fraction']:.0%} pushed past the goal"),
        PaperRow("side push: D_g=500 µm fixed", "converges in all cases but slowly",
                 f"{s500['converged_fraction']:.0%} converged, {s500['mean_attempts_all']:.1f} mean attempts"),
        PaperRow("side push: learning (lin, K_s=0.9) fastest", "yes",
                 f"{best['mean_attempts_all']:.1f} mean attempts, {best['converged_fraction']:.0%} converged"),
    ] + [PaperRow(f"side push N_p, {label}", "Fig 12 (bars)",
                  f"{s['mean_attempts_all']:.1f} ({s['converged_fraction']:.0%} converged)")
         for label, s in summaries.items()]
    return summary, paper
