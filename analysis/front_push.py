"""Figs 10–11 — front pushing with the eq 13 learning controller, in closed loop.

Six controllers, K_c ∈ {0, 0.5, 1} × δ(0) ∈ {0, model}, push a 210 µm sphere to a
goal 750 µm beyond it from a robot start 1 mm behind it (§VI-A): ε_p = 75 µm, at
most 10 attempts. The model δ(0) is the fluid model's own (uncalibrated) release
displacement D_p,r, as the paper used its simulated 127 µm. The plant's sphere–glass
gap is calibrated in this task so that its mean release is the measured 300 µm
(:mod:`magctl.studies.release_calibration`), with a ±10 % lognormal scatter of the
sphere's flow mobility (the task's release is then 289 ± 90 µm, against the measured
300 ± 75 µm), camera noise and stick-slip step
variability switched on — the experiment-like plant.
"""

from __future__ import annotations

import numpy as np

from magctl.config import load_model
from magctl.control.push_params import task_defaults
from magctl.control.status import Status
from magctl.loops import Experiment, Variability, geometry
from magctl.plant.fluid.scenarios import release_displacement
from magctl.studies.paper_statistics import ordering_cause, p_none, p_order
from magctl.studies.push import controller_summary, controller_table, run_experiments, trial_path
from magctl.studies.runner import Cause, Computed, PaperRow, StudyContext, claim

NAME = "front-push"
TITLE = "Figs 10–11 — front pushing: six controllers in closed loop"
ORDER = 50
DEFAULT_TRIALS = 100
_DEFAULTS = task_defaults("front")
EPS_UM = _DEFAULTS["eps"] / 1e-6  # ε_p of eq 12 (models/push.toml)
MAX_ATTEMPTS = _DEFAULTS["max_attempts"]
PLANT = Variability(release_scatter=0.1)


def model_delta0(conditions: str = "magctl") -> float:
    """The feed-forward δ(0) [m]: the fluid model's release displacement in the paper's set-up, as the paper
    used its simulated one; under the paper's conditions its printed 127 µm (``models/push.toml [release]``)."""
    if conditions == "paper":
        return float(load_model("push").release.model)
    return float(np.ravel(release_displacement())[0])


def steady_error(result: dict) -> float:
    """Median final error of the trials that used every attempt (the loop's steady state), in µm."""
    limit = np.asarray(result["status"]) == Status.ATTEMPT_LIMIT
    final = np.asarray(result["final_error_um"])
    return float(np.median(final[limit] if limit.any() else final))


def landing_probability(mean_um: float, std_um: float, eps_um: float) -> float:
    """Probability that a normal release ``N(mean, std)`` from a push stopped at the goal leaves the sphere
    within ``±eps`` of it: ``Φ((ε − μ)/σ) − Φ((−ε − μ)/σ)``."""
    from scipy.stats import norm

    return float(norm.cdf((eps_um - mean_um) / std_um) - norm.cdf((-eps_um - mean_um) / std_um))


def model_only_cause(d0: float, mu: float, sigma: float, attempts: float, fastest: float) -> Cause:
    """Why the model δ(0) without learning is not slow, or not fast: a push aimed δ(0) past the goal leaves the
    sphere ``δ(0) − R`` from it, ``R ~ N(μ, σ)`` the task's release; within ε_p of the mean release the model
    alone lands in the band at once, beyond it every push keeps the error."""
    if abs(d0 - mu) <= EPS_UM:
        hit = landing_probability(d0 - mu, sigma, EPS_UM)
        return Cause(f"δ(0) = {d0:.0f} µm (the release of the paper's set-up, robot backing straight) is "
                     f"{d0 - mu:+.0f} µm off the task's mean release {mu:.0f} ± {sigma:.0f} µm, inside ε_p = "
                     f"{EPS_UM:.0f} µm, so without learning a push lands within ε_p with probability {hit:.0%} "
                     f"per attempt: the model alone is fast on this plant ({attempts:.1f} mean attempts).",
                     hit >= 0.5 and attempts <= fastest)
    return Cause(f"δ(0) = {d0:.0f} µm (the release of the paper's set-up, robot backing straight) is {d0 - mu:+.0f} µm "
                 f"off the task's mean release {mu:.0f} µm, beyond ε_p = {EPS_UM:.0f} µm, and without learning every "
                 "push keeps that error.", attempts > fastest)


def saving(mean_attempts: dict[str, float], kc: str) -> float:
    """Attempts the model δ(0) saves at gain ``kc`` (negative: it costs attempts)."""
    zero = mean_attempts[f"K_c={kc}, δ(0)=0"]
    model = next(v for k, v in mean_attempts.items() if k.startswith(f"K_c={kc},") and not k.endswith("δ(0)=0"))
    return zero - model


def controllers(delta_model: float) -> dict[str, Experiment]:
    out = {}
    for kc in (0.0, 0.5, 1.0):
        for tag, d0 in (("δ(0)=0", 0.0), (f"δ(0)={delta_model * 1e6:.0f} µm", delta_model)):
            label = f"K_c={kc:g}, {tag}"
            out[label] = Experiment("front", task=dict(kc=kc, delta0=d0),
                                    max_frames=4000, variability=PLANT, label=label)
    return out


def compute(ctx: StudyContext) -> Computed:
    """Run the six controllers and reduce their trials; trial 0 of the fastest one kept for the GIF."""
    n = ctx.n_trials(DEFAULT_TRIALS)
    d_model = model_delta0(ctx.conditions)
    exps = controllers(d_model)
    runs, _ = run_experiments(ctx, exps, n)
    summaries = {label: controller_summary(r) for label, r in runs.items()}
    best = min(summaries, key=lambda k: summaries[k]["mean_attempts_all"])
    results = {"trials_per_controller": n, "epsilon_um": EPS_UM, "model_delta0_um": d_model * 1e6,
               "naive_steady_error_um": steady_error(runs["K_c=0, δ(0)=0"]), "controllers": summaries,
               "plant": PLANT.describe()}
    return Computed(results, {"runs": runs, "animated": trial_path(ctx, exps[best])})


def draw(computed: Computed, ctx: StudyContext) -> list:
    """Fig 10 (converged vs attempts), Fig 11 (error vs attempt) and a GIF of one push."""
    from magctl.studies.figures import animate_trial, plot_convergence, plot_errors

    r, runs = computed.results, computed.data["runs"]
    n = r["trials_per_controller"]
    return [
        plot_convergence(r["controllers"], ctx.figure_path("front_push_convergence"),
                         f"Front pushing, {n} trials per controller (cf. Fig 10)", MAX_ATTEMPTS),
        plot_errors({k: runs[k] for k in ("K_c=0, δ(0)=0", "K_c=0.5, δ(0)=0", "K_c=1, δ(0)=0")},
                    ctx.figure_path("front_push_errors"), "Front pushing error (cf. Fig 11)", EPS_UM),
        animate_trial(computed.data["animated"], ctx.figure_path("front_push", ".gif"), geometry("front")["goal"]),
    ]


def summarise(computed: Computed) -> tuple[list[str], list[PaperRow]]:
    """The controller table and the paper's front-push claims beside ours."""
    r = computed.results
    summaries, n, steady_naive = r["controllers"], r["trials_per_controller"], r["naive_steady_error_um"]
    naive = summaries["K_c=0, δ(0)=0"]
    kc1 = {k: v for k, v in summaries.items() if k.startswith("K_c=1,")}
    kc05 = {k: v for k, v in summaries.items() if k.startswith("K_c=0.5,")}
    mean_att = {k: v["mean_attempts_all"] for k, v in summaries.items()}
    summary = [
        f"{n} trials per controller; plant: {r['plant']}.",
        f"Model δ(0) = {r['model_delta0_um']:.0f} µm (the fluid model's D_p,r; paper's simulation: 127 µm).",
        "",
        *controller_table(summaries, MAX_ATTEMPTS, ("final error (µm, median)", "final_error_um_median")),
    ]
    summary += ["", f"Naïve controller's steady error: {steady_naive:.0f} µm (paper: about 200 µm)."]
    conv = {k: v["converged_fraction"] for k, v in summaries.items()}
    model_only = next(k for k in summaries if k.startswith("K_c=0,") and not k.endswith("δ(0)=0"))
    sec, loop = "§VI-A", "closed loop"
    savings = {kc: saving(mean_att, kc) for kc in ("0.5", "1")}
    fastest_kc1 = min(v["mean_attempts_all"] for v in kc1.values())
    trials = {k: v["attempts_all"] for k, v in summaries.items()}
    rel = load_model("front_release").provenance

    def with_d0(kc: str) -> str:
        return next(k for k in summaries if k.startswith(f"K_c={kc},") and not k.endswith("δ(0)=0"))

    mu, sigma = rel.release_mean * 1e6, rel.release_std * 1e6
    d0 = r["model_delta0_um"]
    hit = landing_probability(mu, sigma, EPS_UM)
    slower_05 = [k for k in kc1 if mean_att[k] >= mean_att[k.replace("K_c=1,", "K_c=0.5,")]]
    paper = [
        claim(sec, "naïve front push (K_c = 0, δ(0) = 0) never gets within ε_p", "never (Fig 10)",
              f"{naive['converged_fraction']:.0%} converged", loop, holds=naive["converged_fraction"] < 0.05,
              p_paper=p_none(naive["converged_fraction"]),
              cause=Cause(f"the task's release is {mu:.0f} ± {sigma:.0f} µm (models/front_release.toml), so a push "
                          f"that stops at the goal leaves the sphere within ε_p = {EPS_UM:.0f} µm with probability "
                          f"{hit:.0%} per attempt (normal release).", hit >= 0.05)),
        claim(sec, "naïve steady error ≈ 200 µm (300 µm release less ≈ 100 µm servo overshoot)", "≈ 200 µm",
              f"{steady_naive:.0f} µm (median final error of the trials that used all attempts)", loop,
              holds=150 <= steady_naive <= 250,
              cause=Cause(f"the naïve error is the release ({mu:.0f} µm in the task, {abs(steady_naive - mu):.0f} µm "
                          f"from the steady error) and the task's release is below the paper's measured 300 ± 75 µm "
                          "(the robot turns before it backs away, docs/fluid.md §5).",
                          abs(steady_naive - mu) < EPS_UM and mu < 225)),
        claim(sec, "model δ(0) without learning (K_c = 0) converges, but slowly", "possible, many attempts",
              f"{conv[model_only]:.0%} converged, {mean_att[model_only]:.1f} mean attempts (K_c = 1 best: "
              f"{fastest_kc1:.1f})", loop,
              holds=conv[model_only] > naive["converged_fraction"] and mean_att[model_only] > fastest_kc1,
              cause=model_only_cause(d0, mu, sigma, mean_att[model_only], fastest_kc1)),
        claim(sec, "K_c = 1 (critically damped) converges faster than K_c = 0.5", "yes (Fig 10)",
              f"{fastest_kc1:.2f} vs {min(v['mean_attempts_all'] for v in kc05.values()):.2f} mean attempts", loop,
              holds=all(mean_att[k] < mean_att[k.replace("K_c=1,", "K_c=0.5,")] for k in kc1), ordering=True,
              p_paper=min(p_order(trials[k], trials[k.replace("K_c=1,", "K_c=0.5,")]) for k in kc1),
              cause=Cause(f"K_c = 0.5 is as fast or faster for {', '.join(k.split(', ')[1] for k in slower_05)}.",
                          bool(slower_05))),
        claim(sec, "model δ(0) with learning saves ≈ 1 attempt", "≈ 1 attempt",
              ", ".join(f"{v:+.2f} at K_c = {kc}" for kc, v in savings.items()), loop,
              holds=min(savings.values()) >= 0.5, opposite=savings["1"] < -0.2, ordering=True,
              p_paper=min(p_order(trials[with_d0(kc)], trials[f"K_c={kc}, δ(0)=0"]) for kc in ("0.5", "1")),
              cause=(Cause(f"the model δ(0) = {d0:.0f} µm is {d0 - mu:+.0f} µm off the task's mean release "
                           f"{mu:.0f} µm, so the first push misses the goal by about that instead of the "
                           f"{mu:.0f} µm a δ(0) = 0 push leaves.", True) if abs(d0 - mu) > mu
                     else ordering_cause(with_d0("1"), "K_c=1, δ(0)=0", trials))),
    ] + [PaperRow(f"front push N_p, {label}", "Fig 10 (bars)",
                  f"{s['mean_attempts_all']:.2f} ({s['converged_fraction']:.0%} converged)", model=loop)
         for label, s in summaries.items()]
    return summary, paper
