"""Fig 14 — mean positioning error versus attempt for the best front and side controllers.

Declares ``REUSES = ("front-push", "side-push")``: in ``magctl reproduce`` it takes those two
controllers' trials from the run's trial cache, where the front-push and side-push studies
left them, and says so in its summary; run alone it runs just the two controllers.
"""

from __future__ import annotations

import numpy as np
from scipy.stats import norm

from magctl.control.status import Status
from magctl.studies import runner as studies
from magctl.studies.paper_statistics import p_all
from magctl.studies.push import carried_errors, controller_summary, reuse_note, run_experiments
from magctl.studies.runner import Cause, Computed, PaperRow, StudyContext, claim

NAME = "convergence"
TITLE = "Fig 14 — error versus attempt for the best front and side controllers"
ORDER = 52
DEFAULT_TRIALS = 100
REUSES = ("front-push", "side-push")


def attempts_until(summary: dict, share: float) -> int | None:
    """First attempt by which ``share`` of the trials had converged (None if never)."""
    hits = [a for a, f in enumerate(summary["converged_by_attempt"], start=1) if f >= share - 1e-12]
    return hits[0] if hits else None


def compute(ctx: StudyContext) -> Computed:
    """Errors after every attempt of the best front (K_c=1, model δ(0)) and side (lin, K_s=0.9) controllers."""
    n = ctx.n_trials(DEFAULT_TRIALS)
    front, side = studies.get("front-push"), studies.get("side-push")
    f_exp = front.controllers(front.model_delta0(ctx.conditions))
    f_label = next(k for k in f_exp if k.startswith("K_c=1,") and "δ(0)=0" not in k)
    s_label = side.BEST
    runs, sources = run_experiments(ctx, {f_label: f_exp[f_label], s_label: side.experiments()[s_label]}, n)
    f_err, s_err = carried_errors(runs[f_label]), carried_errors(runs[s_label])
    f_sum, s_sum = controller_summary(runs[f_label]), controller_summary(runs[s_label])
    results = {
        "front_controller": f_label, "side_controller": s_label, "trials": n,
        "front_mean_error_um": np.nanmean(f_err, axis=0).tolist(),
        "side_mean_error_um": np.nanmean(s_err, axis=0).tolist(),
        "front_all_converged_after_attempts": attempts_until(f_sum, 1.0),
        "side_all_converged_after_attempts": attempts_until(s_sum, 1.0),
        "front_95pct_converged_after_attempts": attempts_until(f_sum, 0.95),
        "side_95pct_converged_after_attempts": attempts_until(s_sum, 0.95),
        "side_late_overshot_fraction": late_overshot(runs[s_label], PAPER_ALL_WITHIN["side"], side.EPS_UM),
        "trials_from_study": sources,
    }
    return Computed(results, {"front_error_um": f_err, "side_error_um": s_err,
                              "front_converged_by_attempt": f_sum["converged_by_attempt"],
                              "side_converged_by_attempt": s_sum["converged_by_attempt"],
                              "front_eps_um": front.EPS_UM, "side_eps_um": side.EPS_UM,
                              "front_max_attempts": front.MAX_ATTEMPTS, "side_max_attempts": side.MAX_ATTEMPTS})


def late_overshot(result: dict, attempt: int, eps_um: float) -> float | None:
    """Among the trials not within ε_p by ``attempt``, the share whose sphere had been pushed more than ε_p
    past the goal by then (None when every trial was within ε_p)."""
    status, attempts = np.asarray(result["status"]), np.asarray(result["attempts"])
    late = ~((status == Status.CONVERGED) & (attempts <= attempt))
    if not late.any():
        return None
    signed = np.asarray(result["signed_error_um"])[:, :attempt + 1]
    return float(np.mean(np.nanmin(signed[late], axis=1) < -eps_um))


PAPER_ALL_WITHIN = {"front": 4, "side": 10}
"""Fig 14's caption: all experiments within ε_p after 4 attempts (front) and 10 (side)."""


def share_within(converged_by_attempt: list, attempt: int) -> float:
    """Share of the trials within ε_p by ``attempt`` (the last value past the attempt limit)."""
    return float(converged_by_attempt[min(attempt, len(converged_by_attempt)) - 1])


def draw(computed: Computed, ctx: StudyContext) -> list:
    """Fig 14: mean and median error versus attempt, front and side side by side, with the paper's
    claim (all trials within ε_p by attempt 4 front, 10 side) marked and our share of trials there."""
    from magctl.studies.figures import pyplot, save_figure

    plt = pyplot()
    r, d = computed.results, computed.data
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.6))
    for ax, side in zip(axes, ("front", "side"), strict=True):
        err, eps = d[f"{side}_error_um"], d[f"{side}_eps_um"]
        xs = np.arange(err.shape[1])
        lo, mid, hi = np.nanpercentile(err, [25, 50, 75], axis=0)
        ax.plot(xs, np.nanmean(err, axis=0), "o-", color="C0", ms=5, lw=2.2, zorder=3,
                label=f"{side}: {r[f'{side}_controller']}: mean")
        ax.plot(xs, mid, "s--", color="C1", ms=3, lw=1.0, zorder=4, label="median")
        ax.fill_between(xs, lo, hi, color="C1", alpha=0.15, lw=0, label="25–75 % of trials")
        ax.axhline(eps, color="k", ls=":", lw=1.0, label=f"ε_p = {eps:g} µm")
        claim = PAPER_ALL_WITHIN[side]
        share = share_within(d[f"{side}_converged_by_attempt"], claim)
        ax.axvline(claim, color="C3", ls="-.", lw=1.2,
                   label=f"paper: all within ε_p by attempt {claim}\n(ours: {share:.0%} of {r['trials']} trials)")
        ax.annotate(f"ours: {share:.0%} within ε_p", (claim, eps), textcoords="offset points", xytext=(5, 6),
                    color="C3", fontsize=8)
        ax.set_yscale("log")
        ax.set_xlabel("pushing attempt (count; 0 = before the first push)")
        ax.set_ylabel("positioning error (µm)")
        ax.set_title(f"{side} pushing", fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7.5)
    fig.suptitle(f"Positioning error over {r['trials']} trials (cf. Fig 14: all experiments within ε_p "
                 "after 4 attempts for front pushing, and 10 for side pushing)", fontsize=10)
    return [save_figure(fig, ctx.figure_path("convergence"), dpi=120)]


def summarise(computed: Computed) -> tuple[list[str], list[PaperRow]]:
    """Attempts until every (and 95 % of the) trials were within ε_p, against the paper's Fig 14."""
    r, d = computed.results, computed.data
    f_label, s_label = r["front_controller"], r["side_controller"]
    f_all, s_all = r["front_all_converged_after_attempts"], r["side_all_converged_after_attempts"]
    f_95, s_95 = r["front_95pct_converged_after_attempts"], r["side_95pct_converged_after_attempts"]

    def after(a, limit: int) -> str:
        return f"after {a} attempts" if a is not None else f"not within the {limit}-attempt limit"

    def every(a, limit: int, by_attempt: list) -> str:
        if a is not None:
            return after(a, limit)
        return f"{after(a, limit)} ({1 - by_attempt[-1]:.0%} still outside then)"

    f_lim, s_lim = d["front_max_attempts"], d["side_max_attempts"]
    summary = [f"Best front controller {f_label}: every trial within ε_p (eq 12, as the task measures it) "
               f"{every(f_all, f_lim, d['front_converged_by_attempt'])}, 95 % {after(f_95, f_lim)}; "
               "paper: all after 4.",
               f"Best side controller {s_label}: every trial within ε_p "
               f"{every(s_all, s_lim, d['side_converged_by_attempt'])}, "
               f"95 % {after(s_95, s_lim)}; paper: all after 10.",
               "", reuse_note(r["trials_from_study"], NAME)]
    f_by, s_by = d["front_converged_by_attempt"], d["side_converged_by_attempt"]
    sigma = release_std_um()
    miss = 2.0 * float(norm.cdf(-d["front_eps_um"] / sigma))
    late = r["side_late_overshot_fraction"] if r["side_late_overshot_fraction"] is not None else 0.0
    paper = [
        claim("§VI-A", "Fig 14: with the best front controller every trial is within ε_p after 4 attempts",
              "all after 4", f"{after(f_all, f_lim)}; {f_by[3]:.0%} by attempt 4, 95 % {after(f_95, f_lim)} "
              f"({f_label})", "closed loop", holds=f_all is not None and f_all <= 4, p_paper=p_all(f_by[3]),
              cause=Cause(f"the task's release scatters by ±{sigma:.0f} µm (1σ, models/front_release.toml), so a push "
                          f"aimed at the goal lands outside the ±{d['front_eps_um']:.0f} µm band with probability "
                          f"{miss:.0%} per attempt.", miss >= 0.05)),
        claim("§VI-B", "Fig 14: with the best side controller every trial is within ε_p after 10 attempts",
              "all after 10", f"{after(s_all, s_lim)}; {s_by[9]:.0%} by attempt 10, 95 % {after(s_95, s_lim)} "
              f"({s_label})", "closed loop", holds=s_all is not None and s_all <= 10, p_paper=p_all(s_by[9]),
              cause=Cause(f"{late:.0%} of the trials still outside ε_p = {d['side_eps_um']:g} µm at attempt 10 "
                          "had been pushed past the goal by then, and a sphere past the goal can be brought back "
                          "only by a pass from its other side.", late >= 0.5)),
    ]
    return summary, paper


def release_std_um() -> float:
    """The closed loop's release scatter (1σ over all logged attempts, µm) from the identified release map."""
    from magctl.config import load_model

    return float(load_model("front_release").provenance.release_std) * 1e6
