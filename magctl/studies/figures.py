"""Figures shared by the studies: matplotlib set-up, the push studies' convergence and error
plots and their GIFs. Only the studies' ``draw`` steps import this module."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from magctl.studies.push import carried_errors


def pyplot():
    """``matplotlib.pyplot`` on the Agg backend (files only, no display)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: Path, dpi: int = 120) -> Path:
    """Lay ``fig`` out, write it to ``path`` and release it; returns ``path``."""
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    pyplot().close(fig)
    return path


def plot_convergence(summaries: dict[str, dict], path: Path, title: str, max_attempts: int) -> Path:
    """Fig 10/12 style: fraction of converged trials versus pushing attempts."""
    plt = pyplot()
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
    return save_figure(fig, path)


def plot_errors(results: dict[str, dict], path: Path, title: str, eps_um: float, log: bool = False) -> Path:
    """Fig 11/13 style: error versus attempt — median, interquartile band and trial 0 of each controller."""
    plt = pyplot()
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
    return save_figure(fig, path)


def animate_trial(trial: dict, path: Path, goal) -> Path:
    """A GIF of one trial's trajectories (:func:`magctl.studies.push.trial_path`)."""
    from magctl.studies.animate import animate_push

    return animate_push(trial["t"], trial["robot_xy"], trial["robot_heading"], trial["spheres_xy"], path,
                        goal=goal, title=trial["title"])
