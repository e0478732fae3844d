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
* the trial's last contact release ``R_c``: the same sphere in the notch repeats its release.

:func:`attempt_log` records these from a batch of closed-loop trials (the same chunked
``simulate`` calls as :func:`magctl.studies.trials.run_push_trials`, so trial ``k`` of seed ``s``
is the trial the studies run). :func:`identify` bins ``L`` and stores, per bin, the contact
probability and the empirical quantiles of ``R`` (later attempts with contact: per bin of
``R_c``) — a conditional distribution per bin: it keeps the bimodal overshoot of the first
attempt and the heteroscedastic scatter. :func:`write_model` writes it with its provenance (controllers, trials,
seed) to ``models/front_release.toml``; ``magctl.stability.iteration`` samples it
(``magctl stability front --model identified``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.special import ndtri
from scipy.stats import rankdata

from magctl.control.push.common import task_defaults
from magctl.control.push.front import PUSH
from magctl.control.status import Status
from magctl.core import simulate
from magctl.core.units import UM
from magctl.loops import Experiment, geometry, push_loop

STATUS, ATTEMPT, PHASE = "controller/task.status", "controller/task.attempt", "controller/task.phase"
CORRECTION, SPHERES, ROBOT = "controller/task.correction", "plant/spheres.spheres", "plant/robot.position"
RECORD = [STATUS, ATTEMPT, PHASE, CORRECTION, SPHERES, ROBOT]
CONTACT_MARGIN = 10 * UM
"""Robot–sphere centre distance above the notch contact (models/push.toml ``contact``) still counted as touching."""
QUANTILES = tuple(np.round(np.linspace(0.0, 1.0, 21), 4))
"""Probability levels of the stored release quantiles (every 5 %)."""
MIN_CELL = 8
"""Fewest attempts for a (bin, contact) cell to get its own quantiles; sparser cells use the bin's pooled ones."""
N_BINS = 20
"""Push-length bins of the later attempts (equal-count)."""
N_BINS_FIRST = 2
"""Push-length bins of the first attempt (its push length is the goal distance plus δ(0): one per δ(0))."""


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
        res = simulate(diagram, steps, batch=batch, seed=seed, trials=trials, record=RECORD, state=state)
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
                                             "error_after", "lateral_after", "min_gap", "mobility_score")}
    gap = np.linalg.norm(sphere - robot, axis=-1)
    for b in range(batch):
        bumps = np.flatnonzero(np.diff(att[b]) > 0) + 1  # frames where attempt i was measured
        start = start0[b]
        for i, k1 in enumerate(bumps, start=1):
            in_att = att[b] == i - 1
            pushing = in_att & (phase[b] == PUSH)
            # δ(i): the law's output while attempt i runs (its update shows only at the measurement frame)
            k_in = np.flatnonzero(in_att)
            delta = float(corr[b, k_in[-1]]) if k_in.size else float(corr[b, 0])
            u = (goal - start) / np.linalg.norm(goal - start)
            e_before = float((goal - start) @ u)
            end = sphere[b, k1]
            e_after = float((goal - end) @ u)
            off = goal - end - e_after * u
            rows["trial"].append(trials[b])
            rows["attempt"].append(i)
            rows["delta"].append(delta)
            rows["push_length"].append(e_before + delta)
            rows["release"].append(e_after + delta)
            rows["error_before"].append(e_before)
            rows["error_after"].append(e_after)
            rows["lateral_after"].append(float(np.linalg.norm(off)))
            rows["min_gap"].append(float(gap[b, pushing].min()) if pushing.any() else np.inf)
            rows["mobility_score"].append(float(score[b]))
            start = end
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


def _scores(x: np.ndarray) -> np.ndarray:
    """Normal scores of ``x`` (ranks mapped through Φ⁻¹)."""
    return ndtri((rankdata(x) - 0.5) / x.size)


def _table(length, release, contact, lateral, n_bins, levels, min_cell, last_contact=None,
           n_contact_bins: int = 0) -> dict:
    """Quantile tables of one attempt class over ``n_bins`` equal-count push-length bins.

    With ``last_contact`` the contact quantiles are over ``n_contact_bins`` equal-count bins of
    it instead (adds ``contact_edges``, ``contact_mean``, ``contact_count``).
    """
    length, release, contact, lateral = (np.asarray(x) for x in (length, release, contact, lateral))
    if length.size < n_bins * min_cell:
        raise ValueError(f"{length.size} attempts are too few to identify {n_bins} bins of at least {min_cell}")
    edges = np.quantile(length, np.arange(1, n_bins) / n_bins)
    idx = np.searchsorted(edges, length, side="right")
    count, lmean, pc = np.zeros(n_bins, int), np.zeros(n_bins), np.zeros(n_bins)
    q_on, q_off, q_lat = (np.zeros((n_bins, levels.size)) for _ in range(3))
    for j in range(n_bins):
        m = idx == j
        if not m.any():
            raise ValueError(f"push-length bin {j} is empty: the attempts have too few distinct lengths")
        count[j], lmean[j], pc[j] = m.sum(), length[m].mean(), contact[m].mean()
        q_lat[j] = np.quantile(lateral[m], levels)
        on, off = m & contact, m & ~contact
        q_on[j] = np.quantile(release[on if on.sum() >= min_cell else m], levels)
        q_off[j] = np.quantile(release[off if off.sum() >= min_cell else m], levels)
    out = {"edges": edges, "count": count, "length_mean": lmean, "p_contact": pc, "quantiles_contact": q_on,
           "quantiles_free": q_off, "quantiles_lateral": q_lat}
    if last_contact is not None:
        sel = contact & np.isfinite(last_contact)
        rc, r = np.asarray(last_contact)[sel], release[sel]
        if rc.size < n_contact_bins * min_cell:
            raise ValueError(f"{rc.size} contact attempts are too few for {n_contact_bins} bins of {min_cell}")
        c_edges = np.quantile(rc, np.arange(1, n_contact_bins) / n_contact_bins)
        cidx = np.searchsorted(c_edges, rc, side="right")
        out.update(contact_edges=c_edges, contact_count=np.bincount(cidx, minlength=n_contact_bins),
                   contact_mean=np.array([rc[cidx == j].mean() for j in range(n_contact_bins)]),
                   quantiles_contact=np.array([np.quantile(r[cidx == j], levels) for j in range(n_contact_bins)]))
    return out


def last_contact_release(log: dict[str, np.ndarray]) -> np.ndarray:
    """Per attempt: the release of the trial's most recent earlier attempt that touched the sphere (NaN before any)."""
    attempt, release, contact = (np.asarray(log[k]) for k in ("attempt", "release", "contact"))
    if np.any(attempt[1:][attempt[1:] > 1] != attempt[:-1][attempt[1:] > 1] + 1):
        raise ValueError("the log must list each trial's attempts in order (attempt_log's layout)")
    out = np.full(attempt.size, np.nan)
    mem = np.nan
    for i in range(attempt.size):
        if attempt[i] == 1:
            mem = np.nan
        out[i] = mem
        if contact[i]:
            mem = release[i]
    return out


def identify(log: dict[str, np.ndarray], *, n_bins: int = N_BINS, n_bins_first: int = N_BINS_FIRST,
             quantiles=QUANTILES, min_cell: int = MIN_CELL) -> dict:
    """The release map from a per-attempt log (metres).

    Two attempt classes: the first attempt (the robot starts from rest behind the sphere, the
    sphere has not been pushed yet) and the later ones (the robot comes back from its retraction).
    In each, ``L`` is split into equal-count bins (``n_bins_first``, ``n_bins``) and each bin
    stores its attempt count, the mean ``L``, the contact probability, and quantiles at
    ``quantiles`` (a cell with fewer than ``min_cell`` attempts takes the bin's pooled attempts):

    * contact, first attempt: of ``R``;
    * contact, later attempts: of ``R`` over ``n_bins`` equal-count bins of ``R_c``, the trial's
      last contact release, instead of ``L``. The same sphere pushed into the notch by the same
      robot repeats its release (in the loop ``R(2) ≈ R(1)`` for most trials, whatever the push
      length), which i.i.d. draws of ``R`` would miss: the release is a state of the attempt map;
    * no contact (the flow moved the sphere into eq 11's band first): of ``R``;
    * of ``lateral``, the sphere's distance off the attempt's line (eq 12 tests the 2-D distance,
      and the next attempt re-aims).

    Returns ``levels``, ``first`` and ``later`` (dicts with ``edges``, ``count``, ``length_mean``,
    ``p_contact``, ``quantiles_contact``, ``quantiles_free``, ``quantiles_lateral``) and the
    pooled ``release_mean``, ``release_std``.
    """
    length, release, contact, lateral, attempt = (np.asarray(log[k]) for k in (
        "push_length", "release", "contact", "lateral_after", "attempt"))
    levels = np.asarray(quantiles, dtype=float)
    first = attempt == 1
    rc = last_contact_release(log)
    tables = {
        "first": _table(length[first], release[first], contact[first], lateral[first], n_bins_first, levels,
                        min_cell),
        "later": _table(length[~first], release[~first], contact[~first], lateral[~first], n_bins, levels,
                        min_cell, rc[~first], n_bins),
    }
    return {"levels": levels, **tables, "release_mean": float(release.mean()), "release_std": float(release.std())}


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


def _num(x) -> str:
    return f"{x:.2f}" if np.isfinite(x) else ("inf" if x > 0 else "-inf")


def _list(a) -> str:
    return "[" + ", ".join(_num(float(x)) for x in np.ravel(a)) + "]"


def _list4(a) -> str:
    return "[" + ", ".join(f"{float(x):.4f}" for x in np.ravel(a)) + "]"


def model_toml(model: dict) -> str:
    """TOML text of an identified model (lengths in µm, two decimals) with its provenance."""
    p = model["provenance"]
    src = (f"fit: magctl.studies.front_release.identify_from_loop(trials={p['trials']}, seed={p['seed']}) — "
           f"{p['attempts']} attempts of the closed-loop front push ({', '.join(p['controllers'])}; plant: "
           f"{p['plant']})")
    eps = task_defaults("front")["eps"]
    lines = [
        "# The front push's release map identified from the closed loop (docs/push-control.md §2).",
        "# Generated by magctl.studies.front_release.write_model(); do not edit by hand:",
        "# tests/studies/test_front_release.py regenerates it and compares.",
        "# R = (P_o - P_s')·u after an attempt, L = (P_o - P_s)·u before it (P_o = P_g + delta·u, eq 10);",
        "# later attempts with contact: R over bins of R_c, the trial's last contact release.",
        "",
        "[provenance]",
        f'controllers = {{ value = "{"; ".join(p["controllers"])}", source = "analysis/front_push.py controllers()" }}',
        f'trials_count = {{ value = {p["trials"]}, source = "{src}" }}',
        f'seed_count = {{ value = {p["seed"]}, source = "root seed of the identification trials" }}',
        f'attempts_count = {{ value = {p["attempts"]}, source = "attempts recorded over all trials" }}',
        f'eps_um = {{ value = {eps / UM:.2f}, source = "models/push.toml front.eps_um at identification" }}',
        "",
        "[map]",
        f'levels_1 = {{ value = {_list(model["levels"])}, source = "probability levels of the quantiles" }}',
        f'release_mean_um = {{ value = {model["release_mean"] / UM:.2f}, source = "mean release over all attempts" }}',
        f'release_std_um = {{ value = {model["release_std"] / UM:.2f}, source = "release std over all attempts" }}',
    ]
    for name, what in (("first", "first attempt"), ("later", "attempts 2 on")):
        t = model[name]
        lines += [
            "", f"[map.{name}]",
            f'edges_um = {{ value = {_list(t["edges"] / UM)}, source = "{src}: {what}, inner edges of the '
            f'push-length bins (equal-count)" }}',
            f'count_1 = {{ value = {_list(t["count"])}, source = "attempts per bin" }}',
            f'length_mean_um = {{ value = {_list(t["length_mean"] / UM)}, source = "mean push length per bin" }}',
            f'p_contact_1 = {{ value = {_list(t["p_contact"])}, source = "share of attempts per bin whose robot '
            f'touched the sphere during PUSH" }}',
        ]
        if "contact_mean" in t:
            lines += [
                f'contact_edges_um = {{ value = {_list(t["contact_edges"] / UM)}, source = "{src}: contact rows are '
                f'bins of the trial\'s last contact release R_c (equal-count)" }}',
                f'contact_count_1 = {{ value = {_list(t["contact_count"])}, source = "contact attempts per R_c bin" }}',
                f'contact_mean_um = {{ value = {_list(t["contact_mean"] / UM)}, source = "mean R_c per bin" }}',
            ]
        on = "release quantiles, contact" if name == "first" else \
            "release quantiles, contact, per bin of the trial's last contact release R_c"
        for key, label in (("quantiles_contact", on),
                           ("quantiles_free", "release quantiles, no contact"),
                           ("quantiles_lateral", "quantiles of the distance off the line")):
            lines += ["", f"[map.{name}.{key}]"]
            for j, row in enumerate(t[key]):
                lines.append(f'bin{j}_um = {{ value = {_list(row / UM)}, source = "{label}" }}')
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
    from magctl.stability.iteration import ReleaseMap, front_attempts_monte_carlo, front_identified_map
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
    from magctl.stability.iteration import ReleaseMap, front_identified_map

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
