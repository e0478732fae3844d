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


LINESTYLES = ("-", "--", "-.", ":")
MARKERS = ("o", "s", "^", "D", "v", "P", "X")


def distinct_style(i: int, n: int) -> dict:
    """Line style of the ``i``-th of ``n`` curves that may coincide: its own colour, a line style
    cycled through ``- -- -. :``, its own marker, a line width shrinking with ``i`` and a z-order
    growing with it, so a later (thinner) curve is drawn on top of an earlier (wider) one and both
    stay visible where they coincide."""
    return {"color": f"C{i % 10}", "ls": LINESTYLES[i % len(LINESTYLES)], "marker": MARKERS[i % len(MARKERS)],
            "lw": 2.6 - 1.4 * i / max(n - 1, 1), "ms": 6.5 - 2.5 * i / max(n - 1, 1), "zorder": 2 + 0.1 * i,
            "markerfacecolor": "none" if i % 2 else f"C{i % 10}"}


def marker_every(i: int, n_points: int, spacing: int | None = None):
    """``markevery`` of the ``i``-th curve: every point for short curves, else every ``spacing``-th
    point starting at ``i mod spacing``, so the markers of coinciding curves do not sit on one another."""
    if spacing is None:
        spacing = 1 if n_points <= 12 else 3
    return (i % spacing, spacing) if spacing > 1 else None


def plot_convergence(summaries: dict[str, dict], path: Path, title: str, max_attempts: int,
                     offset_pct: float = 0.8) -> Path:
    """Fig 10/12 style: share of converged trials versus pushing attempts.

    Each controller has its own colour, line style and marker (:func:`distinct_style`), and its
    curve is shifted up by ``offset_pct`` percentage points times its index, centred on zero, so
    curves that coincide (several controllers at 100 %) stay visible; the y-axis label says so.
    """
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.8, 4.6))
    n = len(summaries)
    for i, (label, s) in enumerate(summaries.items()):
        xs = np.arange(1, len(s["converged_by_attempt"]) + 1)
        n_p = s["mean_attempts_converged"]
        tag = f"N_p = {n_p:.1f}" if n_p is not None else "never"
        shift = offset_pct * (i - (n - 1) / 2)
        ax.step(xs, 100 * np.asarray(s["converged_by_attempt"]) + shift, where="post", label=f"{label} ({tag})",
                markevery=marker_every(i, xs.size), **distinct_style(i, n))
    ax.set_xlim(0.7, max_attempts + 0.3)
    pad = 2 + offset_pct * (n - 1) / 2
    ax.set_ylim(-pad, 100 + pad)
    ax.set_xlabel("pushing attempts (count)")
    ylabel = "converged trials (%)"
    if n > 1 and offset_pct:
        ylabel += f"\n(curves offset by {offset_pct:g} %-points each to stay visible)"
    ax.set_ylabel(ylabel, fontsize=9)
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="lower right")
    return save_figure(fig, path)


def plot_errors(results: dict[str, dict], path: Path, title: str, eps_um: float, log: bool = False) -> Path:
    """Fig 11/13 style: error versus attempt — median, interquartile band and trial 0 of each controller.

    Each controller has its own colour, line style and marker (:func:`distinct_style`), wider lines
    drawn first, so coinciding medians stay visible.
    """
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.8, 4.6))
    n = len(results)
    for i, (label, r) in enumerate(results.items()):
        err = carried_errors(r)
        xs = np.arange(err.shape[1])
        lo, mid, hi = np.nanpercentile(err, [25, 50, 75], axis=0)
        style = distinct_style(i, n)
        ax.plot(xs, mid, label=f"{label}: median", markevery=marker_every(i, xs.size), **style)
        ax.fill_between(xs, lo, hi, color=style["color"], alpha=0.12, lw=0, zorder=1)
        ax.plot(xs, r["error_um"][0], color=style["color"], ls="-", lw=0.7, alpha=0.45, zorder=style["zorder"])
    ax.axhline(eps_um, color="k", ls="--", lw=0.8, label=f"ε_p = {eps_um:g} µm", zorder=1.5)
    ax.plot([], [], color="0.4", ls="-", lw=0.7, alpha=0.6, label="trial 0 (thin faint line, controller's colour)")
    ax.fill_between([], [], [], color="0.4", alpha=0.15, label="25–75 % of trials")
    if log:
        ax.set_yscale("log")
    ax.set_xlabel("pushing attempt (count; 0 = before the first push)")
    ax.set_ylabel("positioning error (µm)")
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    return save_figure(fig, path)


def animate_trial(trial: dict, path: Path, goal) -> Path:
    """A GIF of one trial's trajectories (:func:`magctl.studies.push.trial_path`)."""
    from magctl.studies.animate import animate_push

    return animate_push(trial["t"], trial["robot_xy"], trial["robot_heading"], trial["spheres_xy"], path,
                        goal=goal, title=trial["title"])
