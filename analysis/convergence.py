"""Fig 14 — mean positioning error versus attempt for the best front and side controllers.

Reuses the trials of the ``front-push`` and ``side-push`` studies when they ran in the
same process (``magctl reproduce``); runs just the two controllers otherwise.
"""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from magctl import studies  # noqa: E402
from magctl.push_report import carried_errors, run_experiments  # noqa: E402
from magctl.studies import PaperRow, StudyContext, StudyResult  # noqa: E402

NAME = "convergence"
TITLE = "Fig 14 — error versus attempt for the best front and side controllers"
ORDER = 52
DEFAULT_TRIALS = 100


def first_all_within(err: np.ndarray, eps: float) -> int | None:
    """First attempt after which every trial's (carried) error is within ``eps``."""
    ok = np.nonzero((err <= eps).all(axis=0))[0]
    return int(ok[0]) if ok.size else None


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
        ax.errorbar(xs, np.nanmean(err, axis=0), yerr=np.nanstd(err, axis=0), capsize=2, label=label)
        ax.axhline(eps, color="k", ls="--", lw=0.8, label=f"ε_p = {eps:g} µm")
        ax.set_yscale("log")
        ax.set_xlabel("pushing attempt")
        ax.set_ylabel("positioning error (µm)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(f"Mean ± std error over {n} trials (cf. Fig 14)", fontsize=10)
    fig.tight_layout()
    path = ctx.figure_path("convergence")
    fig.savefig(path, dpi=120)
    plt.close(fig)
    f_all, s_all = first_all_within(f_err, front.EPS_UM), first_all_within(s_err, side.EPS_UM)
    f_95 = next((a for a in range(f_err.shape[1]) if np.mean(f_err[:, a] <= front.EPS_UM) >= 0.95), None)
    s_95 = next((a for a in range(s_err.shape[1]) if np.mean(s_err[:, a] <= side.EPS_UM) >= 0.95), None)
    results = {
        "front_controller": f_label, "side_controller": s_label, "trials": n,
        "front_mean_error_um": np.nanmean(f_err, axis=0).tolist(),
        "side_mean_error_um": np.nanmean(s_err, axis=0).tolist(),
        "front_all_within_eps_after_attempts": f_all, "side_all_within_eps_after_attempts": s_all,
        "front_95pct_within_eps_after_attempts": f_95, "side_95pct_within_eps_after_attempts": s_95,
    }
    summary = [f"Best front controller {f_label}: all trials within ε_p after {f_all} attempts "
               f"(95 % after {f_95}); paper: 4.",
               f"Best side controller {s_label}: all trials within ε_p after {s_all} attempts "
               f"(95 % after {s_95}); paper: 10."]
    paper = [PaperRow("attempts until all trials within ε_p, front (best)", "4", f"{f_all} (95 %: {f_95})"),
             PaperRow("attempts until all trials within ε_p, side (best)", "10", f"{s_all} (95 %: {s_95})")]
    return StudyResult(NAME, results, [path], summary, paper)
