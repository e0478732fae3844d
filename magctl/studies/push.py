"""Reductions and figures shared by the closed-loop push studies (Figs 10–15)."""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from magctl.control.status import Status, status_counts  # noqa: E402
from magctl.loops import Experiment
from magctl.studies.trials import run_push_trials  # noqa: E402

_MEMO: dict[str, dict] = {}


def run_experiments(ctx, exps: dict[str, Experiment], n_trials: int) -> dict[str, dict]:
    """``n_trials`` trials of every experiment, all on one executor at once.

    Each controller runs as few, large lockstep batches as keep the workers busy. Results
    are memoised within a process, so studies that share a controller (``convergence``)
    do not run it twice.
    """
    from magctl.sweep import default_workers, run_sweeps

    keys = {label: repr((exp, n_trials, ctx.seed, ctx.scheduler)) for label, exp in exps.items()}
    todo = {label: exp for label, exp in exps.items() if keys[label] not in _MEMO}
    if todo:
        workers = ctx.workers or default_workers()
        chunks_per_job = max(1, math.ceil(workers / len(todo)))
        jobs = {label: (run_push_trials, n_trials, {"exp": exp}) for label, exp in todo.items()}
        done = run_sweeps(jobs, seed=ctx.seed, chunk_size=max(1, math.ceil(n_trials / chunks_per_job)),
                          scheduler=ctx.scheduler, workers=ctx.workers, progress=not ctx.quiet,
                          desc=f"{len(todo)} controllers")
        for label, result in done.items():
            _MEMO[keys[label]] = result
    return {label: _MEMO[keys[label]] for label in exps}


def carried_errors(result: dict) -> np.ndarray:
    """Error after each attempt ``(B, A+1)`` µm, a finished trial's last error carried forward."""
    err = np.array(result["error_um"], dtype=float)
    for a in range(1, err.shape[1]):
        gap = np.isnan(err[:, a])
        err[gap, a] = err[gap, a - 1]
    return err


def summarise(result: dict) -> dict:
    """Plain numbers of one controller's trials."""
    status = np.asarray(result["status"])
    attempts = np.asarray(result["attempts"])
    max_att = result["error_um"].shape[1] - 1
    conv = status == Status.CONVERGED
    by_attempt = [float(np.mean(conv & (attempts <= a))) for a in range(1, max_att + 1)]
    err = carried_errors(result)
    return {
        "trials": int(status.size),
        "converged_fraction": float(conv.mean()),
        "converged_by_attempt": by_attempt,
        "mean_attempts_converged": float(attempts[conv].mean()) if conv.any() else None,
        "mean_attempts_all": float(np.where(conv, attempts, max_att).mean()),
        "mean_error_um_by_attempt": np.nanmean(err, axis=0).tolist(),
        "std_error_um_by_attempt": np.nanstd(err, axis=0).tolist(),
        "final_error_um_median": float(np.median(result["final_error_um"])),
        "status": status_counts(status),
    }


def overshoot_fraction(result: dict, eps_um: float) -> float:
    """Share of trials whose sphere was pushed more than ``eps_um`` past the goal at some attempt."""
    signed = np.asarray(result["signed_error_um"])
    return float(np.mean(np.nanmin(signed, axis=1) < -eps_um))


def controller_table(summaries: dict[str, dict], max_attempts: int, extra: tuple[str, str] | None = None) -> list[str]:
    """Markdown table of the controllers' convergence; ``extra`` = (column title, summary key) for one more column."""
    head = f"| controller | converged | N_p (converged) | mean attempts (failures at {max_attempts}) |"
    rule = "|---|---|---|---|"
    if extra:
        head, rule = head + f" {extra[0]} |", rule + "---|"
    lines = [head, rule]
    for label, s in summaries.items():
        n_p = s["mean_attempts_converged"]
        row = (f"| {label} | {s['converged_fraction']:.0%} | {'never' if n_p is None else f'{n_p:.2f}'} | "
               f"{s['mean_attempts_all']:.2f} |")
        if extra:
            value = s[extra[1]]
            row += f" {value:.0%} |" if isinstance(value, float) and value <= 1 else f" {value:.0f} |"
        lines.append(row)
    return lines


def plot_convergence(summaries: dict[str, dict], path: Path, title: str, max_attempts: int) -> Path:
    """Fig 10/12 style: fraction of converged trials versus pushing attempts."""
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for label, s in summaries.items():
        xs = np.arange(1, len(s["converged_by_attempt"]) + 1)
        n_p = s["mean_attempts_converged"]
        tag = f"N_p = {n_p:.1f}" if n_p is not None else "never"
        ax.step(xs, 100 * np.asarray(s["converged_by_attempt"]), where="post", label=f"{label} ({tag})")
    ax.set_xlim(1, max_attempts)
    ax.set_ylim(-2, 102)
    ax.set_xlabel("pushing attempts")
    ax.set_ylabel("converged trials (%)")
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def plot_errors(results: dict[str, dict], path: Path, title: str, eps_um: float, log: bool = False) -> Path:
    """Fig 11/13 style: error versus attempt — median, interquartile band and trial 0 of each controller."""
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for i, (label, r) in enumerate(results.items()):
        err = carried_errors(r)
        xs = np.arange(err.shape[1])
        lo, mid, hi = np.nanpercentile(err, [25, 50, 75], axis=0)
        col = f"C{i}"
        ax.plot(xs, mid, color=col, label=label)
        ax.fill_between(xs, lo, hi, color=col, alpha=0.15)
        ax.plot(xs, r["error_um"][0], color=col, ls=":", lw=0.8)
    ax.axhline(eps_um, color="k", ls="--", lw=0.8, label=f"ε_p = {eps_um:g} µm")
    if log:
        ax.set_yscale("log")
    ax.set_xlabel("pushing attempt")
    ax.set_ylabel("positioning error (µm)")
    ax.set_title(title + "\n(line: median; band: 25–75 %; dotted: trial 0)", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def animate_one(exp: Experiment, path: Path, seed: int, goal) -> Path:
    """A GIF of trial 0 of ``exp``, drawn from the simulation."""
    from magctl.studies.animate import animate_push

    r = run_push_trials([0], seed, exp=exp, keep_paths=True)
    return animate_push(r["t"], r["robot_xy"][0], r["robot_heading"][0], r["spheres_xy"][0], path,
                        goal=goal, title=exp.label or exp.kind)
