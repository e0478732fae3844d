"""Fig 14 — mean positioning error versus attempt for the best front and side controllers.

Reuses the trials of the ``front-push`` and ``side-push`` studies when they ran in the
same process (``magctl reproduce``); runs just the two controllers otherwise.
"""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from magctl.studies import runner as studies  # noqa: E402
from magctl.studies.push import carried_errors, run_experiments, summarise  # noqa: E402
from magctl.studies.runner import PaperRow, StudyContext, StudyResult  # noqa: E402

NAME = "convergence"
TITLE = "Fig 14 — error versus attempt for the best front and side controllers"
ORDER = 52
DEFAULT_TRIALS = 100


def attempts_until(summary: dict, share: float) -> int | None:
    """First attempt by which ``share`` of the trials had converged (None if never)."""
    hits = [a for a, f in enumerate(summary["converged_by_attempt"], start=1) if f >= share - 1e-12]
    return hits[0] if hits else None


def run(ctx: StudyContext) -> StudyResult:
    n = ctx.n_trials(DEFAULT_TRIALS)
    front, side = studies.get("front-push"), studies.get("side-push")
    f_exp = front.controllers(front.model_delta0())
    f_label = next(k for k in f_exp if k.startswith("K_c=1,") and "δ(0)=0" not in k)
    s_label = "lin, K_s=0.9"
    runs = run_experiments(ctx, {f_label: f_exp[f_label], s_label: side.experiments()[s_label]}, n)
    f_err, s_err = carried_errors(runs[f_label]), carried_errors(runs[s_label])
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, err, eps, label in ((axes[0], f_err, front.EPS_UM, f"front: {f_label}"),
                                (axes[1], s_err, side.EPS_UM, f"side: {s_label}")):
        xs = np.arange(err.shape[1])
        lo, mid, hi = np.nanpercentile(err, [25, 50, 75], axis=0)
        ax.plot(xs, np.nanmean(err, axis=0), "o-", ms=3, label=f"{label}: mean")
        ax.plot(xs, mid, "s--", ms=3, lw=0.8, label="median, 25–75 % band")
        ax.fill_between(xs, lo, hi, alpha=0.15)
        ax.axhline(eps, color="k", ls="--", lw=0.8, label=f"ε_p = {eps:g} µm")
        ax.set_yscale("log")
        ax.set_xlabel("pushing attempt")
        ax.set_ylabel("positioning error (µm)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(f"Positioning error over {n} trials (cf. Fig 14)", fontsize=10)
    fig.tight_layout()
    path = ctx.figure_path("convergence")
    fig.savefig(path, dpi=120)
    plt.close(fig)
    f_sum, s_sum = summarise(runs[f_label]), summarise(runs[s_label])
    f_all, s_all = attempts_until(f_sum, 1.0), attempts_until(s_sum, 1.0)
    f_95, s_95 = attempts_until(f_sum, 0.95), attempts_until(s_sum, 0.95)
    results = {
        "front_controller": f_label, "side_controller": s_label, "trials": n,
        "front_mean_error_um": np.nanmean(f_err, axis=0).tolist(),
        "side_mean_error_um": np.nanmean(s_err, axis=0).tolist(),
        "front_all_converged_after_attempts": f_all, "side_all_converged_after_attempts": s_all,
        "front_95pct_converged_after_attempts": f_95, "side_95pct_converged_after_attempts": s_95,
    }

    def after(a, limit: int) -> str:
        return f"after {a} attempts" if a is not None else f"not within the {limit}-attempt limit"

    def every(a, limit: int, summ: dict) -> str:
        if a is not None:
            return after(a, limit)
        return f"{after(a, limit)} ({1 - summ['converged_by_attempt'][-1]:.0%} still outside then)"

    f_lim, s_lim = front.MAX_ATTEMPTS, side.MAX_ATTEMPTS
    summary = [f"Best front controller {f_label}: every trial within ε_p (eq 12, as the task measures it) "
               f"{every(f_all, f_lim, f_sum)}, 95 % {after(f_95, f_lim)}; paper: all after 4.",
               f"Best side controller {s_label}: every trial within ε_p {every(s_all, s_lim, s_sum)}, "
               f"95 % {after(s_95, s_lim)}; paper: all after 10."]
    paper = [PaperRow("attempts until all trials within ε_p, front (best)", "4",
                      f"{after(f_all, f_lim)}; 95 % {after(f_95, f_lim)}"),
             PaperRow("attempts until all trials within ε_p, side (best)", "10",
                      f"{after(s_all, s_lim)}; 95 % {after(s_95, s_lim)}")]
    return StudyResult(NAME, results, [path], summary, paper)
