"""The release-model front-push policy and the bound it measures: closed forms on synthetic release maps, and
the identified map's verdict."""

import numpy as np
import pytest
from reference.push_blocks import best_delta, choose, numpy_form
from scipy.stats import norm

from magctl.core.errors import MagctlError
from magctl.core.units import UM
from magctl.stability import front_bound as B
from magctl.stability.iteration import ReleaseMap

EPS = 75 * UM
GOAL = 750 * UM


def synthetic_map(release_of, n_trials=300, attempts=5, seed=0) -> ReleaseMap:
    """Trials of ``attempts`` attempts: the first at L = goal, later ones at push lengths spread over 0–900 µm
    with previous releases spread over 0–500 µm; release = release_of(L, rng)."""
    rng = np.random.default_rng(seed)
    first, length, previous, release = [], [], [], []
    for _ in range(n_trials):
        prev = 0.0
        for i in range(attempts):
            L = GOAL if i == 0 else rng.uniform(0, 900) * UM
            r = release_of(np.array([L]), rng)[0]
            first.append(i == 0)
            length.append(L)
            previous.append(prev)
            release.append(r)
            prev = r
    n = len(first)
    return ReleaseMap(np.array(first), np.array(length), np.array(previous), np.array(release), np.zeros(n),
                      np.zeros(n, dtype=bool), k=15, scale=100 * UM)


def test_a_release_without_scatter_is_hit_on_every_later_attempt():
    """R = L/2 exactly: after the first attempt (which misses: R = 375 µm, δ(0) = 0) the policy asks for the
    δ with |(d + δ)/2 − δ| < ε_p, finds success 1, and every trial converges at attempt 2."""
    m = synthetic_map(lambda L, rng: 0.5 * L)
    policy = B.release_policy(m, eps=EPS, goal=GOAL)
    delta, p = best_delta(policy, np.array([375 * UM, 100 * UM]), np.array([375 * UM, 375 * UM]))
    assert np.all(p == 1.0)
    assert np.all(np.abs(0.5 * (np.array([375, 100]) * UM + delta) - delta) < EPS)
    run = B.policy_attempts(policy, m, 200)
    assert np.all(run["attempts"] == 2) and run["later_success"] == 1.0
    assert policy.first_success == {GOAL: 0.0}


def test_an_independent_normal_release_gives_the_closed_form_window():
    """R ~ N(300, 90²) µm whatever the push: the best δ centres the window on 300 µm and an attempt succeeds
    with 2Φ(ε_p/σ) − 1; the policy's later-attempt success matches within 4 binomial standard errors."""
    sigma = 90 * UM
    m = synthetic_map(lambda L, rng: 300 * UM + sigma * rng.standard_normal(L.shape), n_trials=600)
    policy = B.release_policy(m, eps=EPS, goal=GOAL, k=200, deltas=np.arange(200, 401, 10) * UM)
    delta, _ = best_delta(policy, np.full(50, 400 * UM), np.full(50, 250 * UM))
    assert np.abs(np.median(delta) - 300 * UM) <= 30 * UM
    run = B.policy_attempts(policy, m, 1500, seed=1)
    exact = 2 * norm.cdf(EPS / sigma) - 1
    later = np.count_nonzero(run["attempts"] != 1)  # trials that made a second attempt, at least
    assert run["later_success"] == pytest.approx(exact, abs=4 * np.sqrt(exact * (1 - exact) / later))


def test_split_by_trial_keeps_trials_whole_and_partitions_the_map():
    m = synthetic_map(lambda L, rng: 0.5 * L, n_trials=21, attempts=3)
    halves = [B.split_by_trial(m, part) for part in (0, 1)]
    assert [int(h.first.sum()) for h in halves] == [11, 10]
    assert all(h.first.size == 3 * int(h.first.sum()) and h.first[0] for h in halves)
    assert sorted(np.r_[halves[0].length, halves[1].length]) == sorted(m.length)


def test_later_success_needed_closed_form():
    # 1 + (1 − 0.2)/p = 2.6  →  p = 0.5
    assert B.later_success_needed(0.2, 2.6) == pytest.approx(0.5)
    with pytest.raises(MagctlError, match="cannot be reached"):
        B.later_success_needed(0.2, 1.0)


def test_the_identified_release_leaves_no_half_attempt_to_gain():
    """On the identified map, cross-validated, against eq 13 with K_c = 1 at its better δ(0) (0 or the model's
    release, whichever needs fewer attempts on the map): the release-model policy does not beat it by 0.5 attempts,
    and its later attempts succeed less often than such a gain would need (docs/push-control.md §7)."""
    from magctl.plant.fluid.scenarios import release_displacement

    runs = [B.cross_validated(trials=1500, delta0_kc1=d0) for d0 in (0.0, float(release_displacement()[0]))]
    r = min(runs, key=lambda run: run["kc1_mean_attempts"])
    assert r["gain_attempts"] < 0.5
    first = max(max(f["first_success_by_push_um"].values()) for f in r["folds"].values())
    needed = B.later_success_needed(first, r["kc1_mean_attempts"] - 0.5)
    assert all(f["policy_later_success"] < needed for f in r["folds"].values())


def test_release_policy_law_steps_the_policy():
    """The law block's update (its kernel) is δ ← δ*(|e|, e + δ) of the numpy reference on the masked trials, read
    on the same logged attempts (the others, and a NaN error, keep theirs); its first δ is the policy's δ(0); the
    front push takes it as learning='release'."""
    from magctl.control.push.front import FrontAssemblyTask, FrontPushTask
    from magctl.control.release_model import ReleasePolicyLaw

    m = synthetic_map(lambda L, rng: 0.5 * L)
    policy = B.release_policy(m, eps=EPS, goal=GOAL)
    law = ReleasePolicyLaw("law", policy)
    state = law.initial_state(4)
    assert np.all(law.output(state, {})["y"] == policy.delta0)
    e = np.array([100, -50, 200, np.nan]) * UM
    mask = np.array([True, True, False, True])
    new = law.update_where(state, {"e": e}, mask)
    want, _, rows = choose(policy, np.abs(e[:2]), e[:2] + state["x"][:2])
    np.testing.assert_array_equal(new["x"][:2], want)
    np.testing.assert_array_equal(new["neighbours"][:2], rows)
    np.testing.assert_array_equal(new["x"][2:], state["x"][2:])
    assert np.all(new["neighbours"][2:] == -1)
    ref = numpy_form(law).update_where(state, {"e": e}, mask)
    for key in ("x", "neighbours"):
        np.testing.assert_array_equal(new[key], ref[key])
    task = FrontPushTask(goal=(0.0, 0.0), learning="release")
    assert isinstance(task.law, ReleasePolicyLaw) and task.kernel() is not None   # the release law is compiled too
    with pytest.raises(MagctlError, match="learning='curve' is not one of eq13, release"):
        FrontPushTask(goal=(0.0, 0.0), learning="curve")
    with pytest.raises(MagctlError, match="front-push assembly takes 'eq13'"):
        FrontAssemblyTask(learning="release")
