"""How far a front push that models its own release can beat eq 13 — measured on the identified release map.

Eq 13 with ``K_c`` = 1 sets ``δ(i+1)`` to the last release: it uses one number of the release's history. A
controller that knew the release's conditional distribution given what it can see before an attempt — the
distance ``d`` to the goal and the trial's last release ``R_prev`` (the identified map's predictors,
:class:`~magctl.control.release_model.ReleaseMap`) — would choose the ``δ`` that maximises the chance that
this attempt ends within ε_p (eq 12): the greedy policy of :mod:`magctl.control.release_model`.
:func:`policy_attempts` runs it on a map; :func:`cross_validated` builds it from half the identified trials
and runs it, beside eq 13 with ``K_c`` = 1, on the other half — so the policy is not scored on the attempts
it was chosen from (on the same attempts it "knows" which of them the resampling will draw).

The result (docs/push-control.md §7) bounds what any controller seeing ``(d, R_prev)`` can gain: the greedy
policy maximises each attempt's success; a lower mean would need a later-attempt success above what the
release's scatter about its conditional mean leaves inside ε_p.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial import cKDTree

from magctl.control.release_model import NEIGHBOURS, ReleaseMap, ReleasePolicy, ReleasePolicyLaw, release_policy
from magctl.core.errors import MagctlError
from magctl.core.units import UM
from magctl.stability.iteration import FRONT_EPS, FRONT_GOAL, FRONT_MAX_ATTEMPTS, front_identified_map


def later_success(distance: np.ndarray, eps: float) -> float:
    """Share of the attempts after the first that ended within ``eps``, from an attempt map's ``distance``
    (B, N; NaN after convergence)."""
    later = distance[:, 1:]
    return float((later < eps).sum() / max(np.isfinite(later).sum(), 1))


def policy_attempts(policy: ReleasePolicy, release_map: ReleaseMap, trials: int = 2000, *, eps: float = FRONT_EPS,
                    goal: float = FRONT_GOAL, max_attempts: int = FRONT_MAX_ATTEMPTS, seed: int = 0) -> dict:
    """Run the controller on ``policy`` — :class:`~magctl.control.release_model.ReleasePolicyLaw`, the block the
    front push steps — on ``release_map`` (:func:`~magctl.stability.iteration.front_identified_map`).

    Returns ``attempts`` (B,) (−1 = not converged) and ``later_success`` (:func:`later_success`).
    """
    run = front_identified_map(0.0, 0.0, trials, release_map=release_map, eps=eps, max_attempts=max_attempts,
                               goal=goal, seed=seed, law=ReleasePolicyLaw("release_law", policy))
    return {"attempts": run["attempts"], "later_success": later_success(run["distance"], eps)}


def split_by_trial(release_map: ReleaseMap, part: int, parts: int = 2) -> ReleaseMap:
    """The map of every ``parts``-th identification trial starting at ``part`` (a trial is a first attempt and
    the later ones logged after it)."""
    trial = np.cumsum(release_map.first) - 1
    keep = trial % parts == part
    return dataclasses.replace(release_map, **{name: getattr(release_map, name)[keep] for name in
                                               ("first", "length", "previous", "release", "lateral", "contact")})


def mean_attempts(attempts: np.ndarray, max_attempts: int = FRONT_MAX_ATTEMPTS) -> float:
    """Mean attempts per trial, a trial that did not converge counted at the limit."""
    a = np.asarray(attempts)
    return float(np.where(a > 0, a, max_attempts).mean())


def cross_validated(release_map: ReleaseMap | None = None, trials: int = 2000, *, seed: int = 0,
                    eps: float = FRONT_EPS, delta0_kc1: float = 0.0) -> dict:
    """The policy built on one half of the identified trials and run on the other, both ways, beside eq 13
    with ``K_c`` = 1 (``δ(0)`` = ``delta0_kc1``) on the same half and seed.

    Returns per fold (``"0→1"``, ``"1→0"``) the policy's and eq 13's mean attempts, the policy's later-attempt
    success and first-attempt success by push length, and the mean over the folds of both means and of the
    gain (eq 13 minus policy).
    """
    m = release_map or ReleaseMap.load()
    folds = {}
    for train, test in ((0, 1), (1, 0)):
        policy = release_policy(split_by_trial(m, train), eps=eps, goal=FRONT_GOAL)
        held_out = split_by_trial(m, test)
        run = policy_attempts(policy, held_out, trials, eps=eps, seed=seed)
        kc1 = front_identified_map(1.0, delta0_kc1, trials, release_map=held_out, eps=eps, seed=seed)
        folds[f"{train}→{test}"] = {
            "policy_mean_attempts": mean_attempts(run["attempts"]), "kc1_mean_attempts": mean_attempts(kc1["attempts"]),
            "policy_later_success": run["later_success"],
            "kc1_later_success": later_success(kc1["distance"], eps),
            "policy_delta0_um": policy.delta0 / UM,
            "first_success_by_push_um": {f"{k / UM:.0f}": v for k, v in policy.first_success.items()}}
    policy_mean = float(np.mean([f["policy_mean_attempts"] for f in folds.values()]))
    kc1_mean = float(np.mean([f["kc1_mean_attempts"] for f in folds.values()]))
    return {"folds": folds, "policy_mean_attempts": policy_mean, "kc1_mean_attempts": kc1_mean,
            "gain_attempts": kc1_mean - policy_mean, "trials": trials, "eps_um": eps / UM,
            "conditional_release_std_um": conditional_scatter(m) / UM}


def conditional_scatter(release_map: ReleaseMap, k: int = NEIGHBOURS) -> float:
    """Median, over the logged later attempts, of the release's standard deviation among the ``k`` logged later
    attempts nearest in ``(L, R_prev)``: the scatter no choice of ``δ`` can remove (m; slightly high, as the
    neighbourhood also spans some change of the conditional mean)."""
    m = release_map
    later = np.flatnonzero(~m.first)
    points = np.c_[m.length[later], m.previous[later]] / m.scale
    _, nb = cKDTree(points).query(points, k=k)
    return float(np.median(m.release[later[nb]].std(axis=1)))


def later_success_needed(first_success: float, mean_target: float) -> float:
    """Later-attempt success ``p`` that a mean of ``mean_target`` attempts needs when the first attempt succeeds
    with ``first_success`` and every later one with ``p`` (geometric): ``1 + (1 − p₁)/p = target``."""
    if mean_target <= 1:
        raise MagctlError(f"a mean of {mean_target!r} attempts cannot be reached: every trial makes one")
    return (1.0 - first_success) / (mean_target - 1.0)
