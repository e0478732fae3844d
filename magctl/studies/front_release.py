"""The front push's release map, identified from closed-loop trials (``models/front_release.toml``).

The paper's iteration model of front pushing (eq 13–15) takes the sphere to stop at
``P_s = P_g + δ − D_p,r`` with ``D_p,r`` i.i.d. — a 0th-order plant. The closed loop of
:func:`magctl.loops.push_loop` does not behave so: the servo overshoots after eq 11's stop, and
from the second attempt on the approaching robot's flow pushes the sphere into eq 11's band
before the robot touches it, so how far the sphere ends short of ``P_o`` depends on how far it
had to go. This module measures that map attempt by attempt.

For attempt ``i`` of a trial (``u`` = the attempt's unit pushing direction, sphere ``P_s`` at its
start, ``P_o = P_g + δ(i)u`` of eq 10):

* push length ``L = (P_o − P_s)·u = e_before + δ(i)`` — the predictor (it holds the error before
  the attempt, ``δ`` and the approach distance the sphere has to travel);
* release ``R = (P_o − P_s′)·u = e_after + δ(i)`` with ``P_s′`` the sphere where the task measures
  (end of ``SETTLE``): the attempt map is ``e_after = R(L) − δ(i)``, the paper's eq 14 plant being
  ``R ≡ D_p,r`` (constant);
* contact: whether the robot came within ``contact + CONTACT_MARGIN`` of the sphere during ``PUSH``;
* the trial's previous release ``R_prev``: the same sphere in the notch repeats its release.

:func:`attempt_log` records these from a batch of closed-loop trials (the same chunked
``simulate`` calls as :func:`magctl.studies.trials.run_push_trials`, so trial ``k`` of seed ``s``
is the trial the studies run). :func:`identify` keeps every logged attempt with its predictors
(first or not, ``L``, the previous release) and outcomes (``R``, lateral distance, contact); the
iteration-domain model resamples them by nearest neighbours — a conditional distribution that
keeps the bimodal overshoot of the first attempt, the heteroscedastic scatter and the joint
dependence of the outcomes. :func:`write_model` writes it with its provenance (controllers, trials,
seed) to ``models/front_release.toml``; ``magctl.stability.iteration`` samples it
(``magctl stability front --model identified``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from magctl.control.push.front import PUSH
from magctl.control.push_params import task_defaults
from magctl.control.release_model import MAP_NEIGHBOURS, MAP_SCALE
from magctl.control.status import Status
from magctl.core import simulate
from magctl.core.units import UM
from magctl.loops import Experiment, geometry, push_loop
from magctl.studies.trials import study_engine

STATUS, ATTEMPT, PHASE = "controller/task.status", "controller/task.attempt", "controller/task.phase"
CORRECTION, SPHERES, ROBOT = "controller/task.correction", "plant/spheres.spheres", "plant/robot.position"
RECORD = [STATUS, ATTEMPT, PHASE, CORRECTION, SPHERES, ROBOT]
CONTACT_MARGIN = 10 * UM
"""Robot–sphere centre distance above the notch contact (models/push.toml ``contact``) still counted as touching."""


def attempt_rows(sphere, robot, attempt, phase, correction, goal, start) -> list[dict[str, float]]:
    """The attempts of one front-push trial, from its per-frame record: one row per measured attempt with
    ``attempt`` (1-based), ``delta`` δ(i), ``push_length`` L, ``release`` R, ``error_before``, ``error_after``,
    ``lateral_after``, ``min_gap`` (definitions in the module docstring) and ``follow``: how far the sphere moved
    back along ``u`` from its farthest point after ``PUSH`` to the measurement — the release as §IV-D measured it, the
    distance the sphere follows the retreating robot (NaN when the attempt had no push).

    ``sphere``, ``robot`` (T, 2), ``attempt``, ``phase``, ``correction`` (T,) are the task's frames, ``goal``
    and ``start`` (2,) the goal and the sphere where the first attempt starts. The studies' closed-loop trials
    (:func:`attempt_log`) and a rig's run logs (:mod:`magctl.identify.release`) both read attempts with it.
    """
    rows = []
    gap = np.linalg.norm(sphere - robot, axis=-1)
    goal = np.asarray(goal, float)
    start = np.asarray(start, float)
    for i, k1 in enumerate(np.flatnonzero(np.diff(attempt) > 0) + 1, start=1):   # frames where attempt i is measured
        in_att = attempt == i - 1
        pushing = in_att & (phase == PUSH)
        # δ(i): the law's output while attempt i runs (its update shows only at the measurement frame)
        k_in = np.flatnonzero(in_att)
        delta = float(correction[k_in[-1]]) if k_in.size else float(correction[0])
        u = (goal - start) / np.linalg.norm(goal - start)
        e_before = float((goal - start) @ u)
        end = sphere[k1]
        e_after = float((goal - end) @ u)
        off = goal - end - e_after * u
        k_pushed = np.flatnonzero(pushing)
        # from the sphere's farthest point along u after the push (where the retreat began: the estimate at the
        # push's last frame lags, and one frame of retreat already moves the sphere a robot's step)
        follow = float((sphere[k_pushed[-1]:k1 + 1] @ u).max() - end @ u) if k_pushed.size else float("nan")
        rows.append({"attempt": i, "delta": delta, "push_length": e_before + delta, "release": e_after + delta,
                     "error_before": e_before, "error_after": e_after,
                     "lateral_after": float(np.linalg.norm(off)),
                     "min_gap": float(gap[pushing].min()) if pushing.any() else np.inf, "follow": follow})
        start = end
    return rows


def attempt_log(exp: Experiment, trials, seed: int, *, chunk_frames: int = 150) -> dict[str, np.ndarray]:
    """Per-attempt record of closed-loop front-push trials (metres; one entry per attempt run).

    Returns ``trial``, ``attempt`` (1-based), ``delta`` (δ used), ``push_length`` (L),
    ``release`` (R), ``error_before``, ``error_after`` (signed along the attempt's ``u``),
    ``lateral_after`` (sphere's distance off the attempt's line at the measurement),
    ``min_gap`` (closest robot–sphere centre distance during ``PUSH``; +inf if the push
    phase was skipped), ``contact`` (bool), ``converged`` (eq 12 after the attempt) and
    ``mobility_score`` (the trial's sphere-mobility factor as a standard normal score: the
    plant draws it lognormal with relative spread ``release_scatter``; 0 without scatter), plus
    per-trial ``trial_attempts`` and ``trial_status``.
    """
    if exp.kind != "front":
        raise ValueError(f"attempt_log needs a front-push experiment, got kind {exp.kind!r}")
    trials = list(trials)
    batch = len(trials)
    diagram = push_loop(exp)
    task = diagram.blocks["controller"].blocks["task"]
    eps, contact = float(task.eps), float(task.contact)
    g = geometry("front")
    goal = np.asarray(g["goal"], float)
    chunks: dict[str, list] = {k: [] for k in RECORD}
    state, done_frames = None, 0
    while done_frames < exp.max_frames:
        steps = min(chunk_frames, exp.max_frames - done_frames)
        res = simulate(diagram, steps, batch=batch, seed=seed, trials=trials, record=RECORD, state=state,
                       engine=study_engine())
        state = res.final_state
        for k in RECORD:
            chunks[k].append(res[k])
        done_frames += steps
        if not (res[STATUS][:, -1] == Status.RUNNING).any():
            break
    rec = {k: np.concatenate(v, axis=1) for k, v in chunks.items()}
    score = _mobility_score(state, exp.variability.release_scatter, batch)
    att, phase, corr = rec[ATTEMPT], rec[PHASE], rec[CORRECTION]
    sphere, robot = rec[SPHERES][:, :, 0], rec[ROBOT]
    start0 = np.broadcast_to(np.asarray(g["spheres"], float)[0], (batch, 2))
    rows: dict[str, list] = {k: [] for k in ("trial", "attempt", "delta", "push_length", "release", "error_before",
                                             "error_after", "lateral_after", "min_gap", "follow",
                                             "mobility_score")}
    for b in range(batch):
        for row in attempt_rows(sphere[b], robot[b], att[b], phase[b], corr[b], goal, start0[b]):
            for k, v in row.items():
                rows[k].append(v)
            rows["trial"].append(trials[b])
            rows["mobility_score"].append(float(score[b]))
    out = {k: np.asarray(v, dtype=int if k in ("trial", "attempt") else float) for k, v in rows.items()}
    out["contact"] = out["min_gap"] < contact + CONTACT_MARGIN
    out["converged"] = np.hypot(out["error_after"], out["lateral_after"]) < eps
    out["trial_attempts"] = att[:, -1].astype(int)
    out["trial_status"] = rec[STATUS][:, -1].astype(int)
    return out


def _mobility_score(state: dict, scatter: float, batch: int) -> np.ndarray:
    """The pushed sphere's mobility factor ``m`` of each trial as ``(ln m + σ²/2)/σ`` (standard normal)."""
    if scatter <= 0:
        return np.zeros(batch)
    leaves = [leaf for leaf in state["leaves"] if isinstance(leaf, dict) and "mobility" in leaf]
    if len(leaves) != 1:
        raise RuntimeError(f"expected one sphere block with a mobility state, found {len(leaves)}")
    sig = np.sqrt(np.log1p(scatter**2))
    return (np.log(np.asarray(leaves[0]["mobility"])[:, 0]) + 0.5 * sig**2) / sig


def merge_logs(logs) -> dict[str, np.ndarray]:
    """Concatenate per-attempt logs of several controllers (the per-trial ``trial_*`` entries are dropped)."""
    logs = list(logs)
    keys = [k for k in logs[0] if not k.startswith("trial_")]
    return {k: np.concatenate([lg[k] for lg in logs]) for k in keys}


def previous_release(log: dict[str, np.ndarray]) -> np.ndarray:
    """Per attempt: the release of the same trial's previous attempt (0 for first attempts)."""
    attempt, release = np.asarray(log["attempt"]), np.asarray(log["release"])
    later = attempt > 1
    if np.any(attempt[1:][later[1:]] != attempt[:-1][later[1:]] + 1) or (attempt.size and later[0]):
        raise ValueError("the log must list each trial's attempts in order (attempt_log's layout)")
    out = np.zeros(attempt.size)
    out[1:][later[1:]] = release[:-1][later[1:]]
    return out


def identify(log: dict[str, np.ndarray]) -> dict:
    """The release map from a per-attempt log (metres): the logged attempts with predictors and outcomes.

    Predictors: first attempt or not, push length ``L`` and the previous attempt's release ``R_prev``
    — the attempt-map state besides ``e`` and ``δ``: the same sphere pushed by the same robot
    repeats its release (``K_c = 1``: ``R(2) − R(1)`` has an interquartile range of 57 µm where ``R``
    has 127 µm), and the previous pull-back sets where the robot starts its next approach, so how far
    its flow carries the sphere before contact. Outcomes: ``R``, the distance off the line
    (eq 12 tests the 2-D distance) and contact, kept jointly.
    ``magctl.control.release_model.ReleaseMap`` resamples them by nearest neighbours.

    Returns ``first``, ``length``, ``previous``, ``release``, ``lateral``, ``contact`` (arrays),
    ``neighbours``, ``scale`` and the pooled ``release_mean``, ``release_std``, ``p_contact_later``.
    """
    release, attempt = np.asarray(log["release"]), np.asarray(log["attempt"])
    first = attempt == 1
    if not first.any() or (~first).sum() < MAP_NEIGHBOURS:
        raise ValueError(f"the log needs first attempts and at least {MAP_NEIGHBOURS} later ones")
    return {"first": first, "length": np.asarray(log["push_length"]), "previous": previous_release(log),
            "release": release, "lateral": np.asarray(log["lateral_after"]), "contact": np.asarray(log["contact"]),
            "neighbours": MAP_NEIGHBOURS, "scale": MAP_SCALE, "release_mean": float(release.mean()),
            "release_std": float(release.std()), "p_contact_later": float(np.asarray(log["contact"])[~first].mean())}


# --- the stored model -----------------------------------------------------------------------------
IDENTIFICATION_TRIALS = 200
IDENTIFICATION_SEED = 1
"""The stored model comes from seed 1; the closed-loop study it is checked against runs seed 0."""


def identification_experiments() -> dict[str, Experiment]:
    """The front-push study's six controllers on its plant (``analysis/front_push.py``)."""
    from magctl.studies.runner import get

    mod = get("front-push")
    return mod.controllers(mod.model_delta0())


def identify_from_loop(trials: int = IDENTIFICATION_TRIALS, seed: int = IDENTIFICATION_SEED,
                       exps: dict[str, Experiment] | None = None) -> tuple[dict, dict]:
    """Run ``trials`` closed-loop trials of each controller, return (model, merged log)."""
    exps = identification_experiments() if exps is None else exps
    logs = [attempt_log(exp, range(trials), seed) for exp in exps.values()]
    log = merge_logs(logs)
    model = identify(log)
    plant = next(iter(exps.values())).variability.describe()
    model["provenance"] = {"controllers": list(exps), "trials": int(trials), "seed": int(seed),
                           "attempts": int(log["release"].size), "plant": plant}
    return model, log


def _list(a, fmt: str = "{:.1f}") -> str:
    return "[" + ", ".join(fmt.format(float(x)) for x in np.ravel(a)) + "]"


def model_toml(model: dict) -> str:
    """TOML text of an identified model (lengths in µm, 0.1 µm) with its provenance."""
    p = model["provenance"]
    src = (f"fit: magctl.studies.front_release.identify_from_loop(trials={p['trials']}, seed={p['seed']}) — "
           f"{p['attempts']} attempts of the closed-loop front push ({', '.join(p['controllers'])}; plant: "
           f"{p['plant']})")
    eps = task_defaults("front")["eps"]
    lines = [
        "# The front push's release map identified from the closed loop (docs/push-control.md §2).",
        "# Generated by magctl.studies.front_release.write_model(); do not edit by hand:",
        "# tests/studies/test_front_release.py regenerates it and compares.",
        "# One entry per logged attempt: predictors (first, length = push length L = (P_o - P_s)·u, previous =",
        "# the trial's previous release) and outcomes (release R = (P_o - P_s')·u, lateral = distance off the",
        "# line, contact); magctl.control.release_model.ReleaseMap resamples them by nearest neighbours.",
        "",
        "[provenance]",
        f'controllers = {{ value = "{"; ".join(p["controllers"])}", source = "analysis/front_push.py controllers()" }}',
        f'trials_count = {{ value = {p["trials"]}, source = "{src}" }}',
        f'seed_count = {{ value = {p["seed"]}, source = "root seed of the identification trials" }}',
        f'attempts_count = {{ value = {p["attempts"]}, source = "attempts recorded over all trials" }}',
        f'eps_um = {{ value = {eps / UM:.2f}, source = "models/push.toml front.eps_um at identification" }}',
        f'release_mean_um = {{ value = {model["release_mean"] / UM:.2f}, source = "mean release over all attempts" }}',
        f'release_std_um = {{ value = {model["release_std"] / UM:.2f}, source = "release std over all attempts" }}',
        f'p_contact_later_1 = {{ value = {model["p_contact_later"]:.4f}, source = "share of attempts after the first '
        f'whose robot touched the sphere during PUSH" }}',
        "",
        "[map]",
        f'neighbours_count = {{ value = {model["neighbours"]}, source = "assumed: a later attempt draws among its '
        f'{model["neighbours"]} nearest logged attempts in (L, R_prev)" }}',
        f'scale_um = {{ value = {model["scale"] / UM:.1f}, source = "assumed: both predictors in units of this length '
        f'for the neighbour search" }}',
        f'first_1 = {{ value = {_list(model["first"].astype(int), "{:.0f}")}, source = "{src}: 1 = first attempt" }}',
        f'length_um = {{ value = {_list(model["length"] / UM)}, source = "push length L before the attempt" }}',
        f'previous_um = {{ value = {_list(model["previous"] / UM)}, source = "the trial\'s previous release '
        f'(0 on a first attempt)" }}',
        f'release_um = {{ value = {_list(model["release"] / UM)}, source = "release R after the attempt" }}',
        f'lateral_um = {{ value = {_list(model["lateral"] / UM)}, source = "distance off the pushing line after the '
        f'attempt" }}',
        f'contact_1 = {{ value = {_list(model["contact"].astype(int), "{:.0f}")}, source = "1 = the robot came within '
        f'contact + {CONTACT_MARGIN / UM:.0f} µm of the sphere during PUSH" }}',
    ]
    return "\n".join(lines) + "\n"


def write_model(path: str | Path | None = None, trials: int = IDENTIFICATION_TRIALS,
                seed: int = IDENTIFICATION_SEED) -> Path:
    """Identify the map from the closed loop and write ``models/front_release.toml`` (or ``path``)."""
    from magctl.config import models_dir

    model, _ = identify_from_loop(trials, seed)
    path = Path(path) if path is not None else models_dir() / "front_release.toml"
    path.write_text(model_toml(model))
    return path


# --- agreement with the closed loop --------------------------------------------------------------
def agreement(trials: int = 200, seed: int = 0, *, model_trials: int = 40000, exps=None) -> dict:
    """The identified model's attempt distribution against ``trials`` closed-loop trials per controller.

    The loop runs :func:`magctl.studies.trials.run_push_trials` (the front-push study's trials for
    ``seed``); the model runs :func:`magctl.stability.iteration.front_identified_map` with
    ``model_trials`` draws, and so does the paper's eq 14 plant (``front_attempts_monte_carlo``).
    Mean attempts count a failure as the attempt limit, as the study does.

    Statistics: the loop's curve is a binomial estimate, its standard error at attempt ``a`` is
    ``√(p(1 − p)/trials)`` (at most ``0.5/√trials``: 3.5 points at 200), the mean's is
    ``sd/√trials``; the model's ``model_trials`` draws add ``√(200/model_trials)`` of that. Returns,
    per controller, ``loop`` and ``model`` and ``paper`` (``mean_attempts``, ``converged_by_attempt``),
    ``max_bin_diff`` and ``mean_diff`` (model − loop), ``bin_se`` (per attempt, from the model's p) and
    ``mean_se``.
    """
    from magctl.control.release_model import ReleaseMap
    from magctl.stability.iteration import front_attempts_monte_carlo, front_identified_map
    from magctl.studies.push import controller_summary
    from magctl.studies.trials import run_push_trials

    exps = identification_experiments() if exps is None else exps
    rmap = ReleaseMap.load()
    out = {}
    for label, exp in exps.items():
        kc, d0 = float(exp.task["kc"]), float(exp.task["delta0"])
        s = controller_summary(run_push_trials(range(trials), seed, exp=exp))
        n_max = len(s["converged_by_attempt"])
        att = front_identified_map(kc, d0, model_trials, release_map=rmap, max_attempts=n_max)["attempts"]
        by = np.array([np.mean((att > 0) & (att <= a)) for a in range(1, n_max + 1)])
        counted = np.where(att > 0, att, n_max)
        paper = front_attempts_monte_carlo(kc, d0, trials=model_trials, max_attempts=n_max)
        loop_by = np.asarray(s["converged_by_attempt"])
        out[label] = {
            "loop": {"mean_attempts": s["mean_attempts_all"], "converged_by_attempt": loop_by.tolist()},
            "model": {"mean_attempts": float(counted.mean()), "converged_by_attempt": by.tolist()},
            "paper": {"mean_attempts": float((np.arange(1, n_max + 1) * paper[:-1]).sum() + n_max * paper[-1]),
                      "converged_by_attempt": np.cumsum(paper[:-1]).tolist()},
            "max_bin_diff": float(np.max(np.abs(by - loop_by))),
            "mean_diff": float(counted.mean() - s["mean_attempts_all"]),
            "bin_se": np.sqrt(by * (1 - by) / trials).tolist(),
            "mean_se": float(counted.std() / np.sqrt(trials)),
        }
    return out


def target_power(trials: int = 200, *, repeats: int = 500, mean_tol: float = 0.3, bin_tol: float = 0.05,
                 exps=None, seed: int = 2) -> dict[str, dict[str, float]]:
    """How often a *perfect* model would meet the agreement targets against ``trials`` loop trials.

    The identified map is taken as the truth: ``repeats`` samples of ``trials`` trials are drawn
    from it and compared with its own 40000-draw distribution. Returns, per controller, the
    share of samples with every converged-by-attempt bin within ``bin_tol`` (``p_bins``), with
    the mean attempts within ``mean_tol`` (``p_mean``) and both (``p_both``). This is the ceiling
    the sampling noise of a ``trials``-trial study puts on the targets.
    """
    from magctl.control.release_model import ReleaseMap
    from magctl.stability.iteration import front_identified_map

    exps = identification_experiments() if exps is None else exps
    rmap = ReleaseMap.load()
    out = {}
    for label, exp in exps.items():
        kc, d0 = float(exp.task["kc"]), float(exp.task["delta0"])
        ref = front_identified_map(kc, d0, 40000, release_map=rmap, seed=seed - 1)["attempts"]
        n_max = int(task_defaults("front")["max_attempts"])
        by = np.array([np.mean((ref > 0) & (ref <= a)) for a in range(1, n_max + 1)])
        mean = np.where(ref > 0, ref, n_max).mean()
        s = front_identified_map(kc, d0, trials * repeats, release_map=rmap, seed=seed)["attempts"]
        s = s.reshape(repeats, trials)
        sby = np.stack([np.mean((s > 0) & (s <= a), axis=1) for a in range(1, n_max + 1)], axis=1)
        ok_b = np.max(np.abs(sby - by), axis=1) <= bin_tol
        ok_m = np.abs(np.where(s > 0, s, n_max).mean(axis=1) - mean) <= mean_tol
        out[label] = {"p_bins": float(ok_b.mean()), "p_mean": float(ok_m.mean()),
                      "p_both": float((ok_b & ok_m).mean())}
    return out
