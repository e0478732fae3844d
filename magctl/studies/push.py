"""Reductions shared by the closed-loop push studies (Figs 10–15); their figures are in
:mod:`magctl.studies.figures`. Nothing here imports matplotlib."""

from __future__ import annotations

import math

import numpy as np

from magctl.control.status import Status, status_counts
from magctl.loops import Experiment
from magctl.studies.trials import run_push_trials


def trials_key(exp: Experiment, n_trials: int, seed: int) -> str:
    """What identifies ``n_trials`` trials of ``exp`` from root ``seed`` in a trial cache.

    The executor is not part of it: trial ``k``'s result does not depend on where it ran.
    """
    return repr(("push-trials", exp, int(n_trials), int(seed)))


def run_experiments(ctx, exps: dict[str, Experiment], n_trials: int) -> tuple[dict[str, dict], dict[str, str]]:
    """``n_trials`` trials of every experiment, all on one executor at once, under ``ctx.conditions``.

    Each controller runs as few, large lockstep batches as keep the workers busy.
    Trials already in ``ctx.trial_cache`` — stored by this study or by one it names in
    ``REUSES`` — are taken from there; the rest are run and stored under ``ctx.study``.

    Parameters
    ----------
    ctx : StudyContext
    exps : dict of str to Experiment
        Controllers by label.
    n_trials : int

    Returns
    -------
    results : dict of str to dict
        :func:`~magctl.studies.trials.run_push_trials` output of each label.
    sources : dict of str to str
        The study whose run produced each label's trials (``ctx.study`` when run here).
    """
    from magctl.studies.conditions import conditioned
    from magctl.sweep import default_workers, run_sweeps

    exps = {label: conditioned(exp, ctx.conditions) for label, exp in exps.items()}
    allowed = (ctx.study, *ctx.reuses)
    keys = {label: trials_key(exp, n_trials, ctx.seed) for label, exp in exps.items()}
    found = {label: ctx.trial_cache.lookup(key, allowed) for label, key in keys.items()}
    todo = {label: exp for label, exp in exps.items() if found[label] is None}
    if todo:
        workers = ctx.workers or default_workers()
        chunks_per_job = max(1, math.ceil(workers / len(todo)))
        jobs = {label: (run_push_trials, n_trials, {"exp": exp}) for label, exp in todo.items()}
        done = run_sweeps(jobs, seed=ctx.seed, chunk_size=max(1, math.ceil(n_trials / chunks_per_job)),
                          scheduler=ctx.scheduler, workers=ctx.workers, progress=not ctx.quiet,
                          desc=f"{ctx.study}: {len(todo)} controllers × {n_trials} trials")
        for label, result in done.items():
            ctx.trial_cache.store(keys[label], ctx.study, result)
            found[label] = (ctx.study, result)
    return {label: found[label][1] for label in exps}, {label: found[label][0] for label in exps}


def path_key(exp: Experiment, seed: int) -> str:
    """What identifies the trajectories of trial 0 of ``exp`` from root ``seed`` in a trial cache."""
    return repr(("push-path", exp, int(seed)))


def trial_path(ctx, exp: Experiment) -> dict:
    """Trial 0 of ``exp`` with its trajectories, for a GIF: ``t`` (s), ``robot_xy`` ``(T, 2)`` (m),
    ``robot_heading`` ``(T,)`` (rad), ``spheres_xy`` ``(T, N, 2)`` (m) and ``title``.

    Taken from ``ctx.trial_cache`` like :func:`run_experiments` takes trials, else run and stored.
    """
    key = path_key(exp, ctx.seed)
    hit = ctx.trial_cache.lookup(key, (ctx.study, *ctx.reuses))
    if hit is not None:
        return hit[1]
    r = run_push_trials([0], ctx.seed, exp=exp, keep_paths=True)
    path = {"t": r["t"], "robot_xy": r["robot_xy"][0], "robot_heading": r["robot_heading"][0],
            "spheres_xy": r["spheres_xy"][0], "title": exp.label or exp.kind}
    ctx.trial_cache.store(key, ctx.study, path)
    return path


def carried_errors(result: dict) -> np.ndarray:
    """Error after each attempt ``(B, A+1)`` µm, a finished trial's last error carried forward."""
    err = np.array(result["error_um"], dtype=float)
    for a in range(1, err.shape[1]):
        gap = np.isnan(err[:, a])
        err[gap, a] = err[gap, a - 1]
    return err


def controller_summary(result: dict) -> dict:
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
        # per trial, the unconverged counted at the attempt budget: for the paper's ten-trial statistics
        "attempts_all": np.where(conv, attempts, max_att).astype(int).tolist(),
        "mean_error_um_by_attempt": np.nanmean(err, axis=0).tolist(),
        "std_error_um_by_attempt": np.nanstd(err, axis=0).tolist(),
        "final_error_um_median": float(np.median(result["final_error_um"])),
        "status": status_counts(status),
    }


def overshoot_fraction(result: dict, eps_um: float) -> float:
    """Share of trials whose sphere was pushed more than ``eps_um`` past the goal at some attempt."""
    signed = np.asarray(result["signed_error_um"])
    return float(np.mean(np.nanmin(signed, axis=1) < -eps_um))


def reuse_note(sources: dict[str, str], study: str) -> str:
    """One sentence saying which controllers' trials came from which other study (or that none did)."""
    by_study: dict[str, list[str]] = {}
    for label, src in sources.items():
        if src != study:
            by_study.setdefault(src, []).append(label)
    if not by_study:
        return "Trials computed by this study (no other study's trials were available to reuse)."
    parts = [f"{', '.join(labels)} from the {src} study" for src, labels in by_study.items()]
    return "Trials reused: " + "; ".join(parts) + "."


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
