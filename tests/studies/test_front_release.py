"""The front push's release map identified from the closed loop (models/front_release.toml)."""

from __future__ import annotations

import numpy as np
import pytest

from magctl.core.errors import MagctlError
from magctl.stability import iteration as S
from magctl.studies import front_release as FR


def _iid_map(n: int = 200000, seed: int = 0) -> S.ReleaseMap:
    """A map whose outcomes are N(300, 75²) µm whatever the predictors: the paper's eq 14 plant."""
    rng = np.random.default_rng(seed)
    first = np.zeros(n, bool)
    first[: n // 4] = True
    length = np.where(first, S.FRONT_GOAL, rng.uniform(-300e-6, 1200e-6, n))
    previous = np.where(first, 0.0, rng.uniform(0.0, 600e-6, n))
    release = rng.normal(300e-6, 75e-6, n)
    return S.ReleaseMap(first, length, previous, release, np.zeros(n), np.ones(n, bool))


def test_paper_plant_is_the_special_case_of_iid_outcomes():
    # With outcomes independent of (L, R_prev) the resampling is i.i.d. N(300, 75²): it must give
    # the paper's distribution, the Markov chain of front_attempts_markov (an independent method).
    rmap = _iid_map()
    for kc in (0.5, 1.0):
        ident = S.front_attempts_identified(kc, 0.0, 40000, release_map=rmap)
        markov = S.front_attempts_markov(kc, 0.0)
        # 40000 draws: binomial SE <= 0.0025 per bin; the finite pool (the ~10^4 entries near the
        # trials' predictors) adds about as much; 0.015 is ~4 SE
        assert np.max(np.abs(np.cumsum(ident[:-1]) - np.cumsum(markov[:-1]))) < 0.015


def test_neighbours_follow_the_predictors():
    # a map whose release equals the previous release: a draw near R_prev returns about R_prev
    n = 4000
    rng = np.random.default_rng(1)
    first = np.zeros(n, bool)
    first[:100] = True
    prev = rng.uniform(0, 500e-6, n)
    rmap = S.ReleaseMap(first, rng.uniform(0, 800e-6, n), prev, prev.copy(), np.zeros(n), np.ones(n, bool))
    r, _, _ = rmap.sample(np.full(5, 400e-6), False, rng, np.array([50e-6, 150e-6, 250e-6, 350e-6, 450e-6]))
    assert np.all(np.abs(r - np.array([50e-6, 150e-6, 250e-6, 350e-6, 450e-6])) < 60e-6)


def test_release_map_rejects_bad_input():
    n = 40
    ok = dict(first=np.r_[np.ones(5, bool), np.zeros(n - 5, bool)], length=np.zeros(n), previous=np.zeros(n),
              release=np.zeros(n), lateral=np.zeros(n), contact=np.ones(n, bool))
    with pytest.raises(MagctlError, match="release"):
        S.ReleaseMap(**{**ok, "release": np.zeros(n - 1)})
    with pytest.raises(MagctlError, match="finite"):
        S.ReleaseMap(**{**ok, "length": np.full(n, np.nan)})
    with pytest.raises(MagctlError, match="first attempts"):
        S.ReleaseMap(**{**ok, "first": np.zeros(n, bool)})
    rmap = S.ReleaseMap(**ok)
    with pytest.raises(MagctlError, match="previous release"):
        rmap.sample(np.zeros(3), False, np.random.default_rng(0))


def test_stored_map_loads_with_its_provenance():
    rmap = S.ReleaseMap.load()
    assert "identify_from_loop(trials=200, seed=1)" in rmap.source
    # first attempts: the sphere is pushed 750 µm from rest and always touched
    assert rmap.contact[rmap.first].mean() > 0.95
    # from attempt 2 the shortest pushes end without contact: the flow moved the sphere into eq 11's band
    later = ~rmap.first
    short = later & (rmap.length < 130e-6)
    long = later & (rmap.length > 350e-6)
    assert rmap.contact[short].mean() < 0.1 and rmap.contact[long].mean() > 0.9


@pytest.mark.slow
def test_regenerating_the_map_gives_the_stored_numbers(tmp_path):
    """Regenerated on this machine, the map matches the stored one in provenance and statistics. Not byte for byte:
    600 chaotic closed-loop trials amplify last-bit floating-point differences between CPUs (the vector code numba
    and numpy pick per machine) into a few attempts more or fewer (3585 against 3588 between two x86-64 machines)."""
    from scipy.stats import ks_2samp

    from magctl.config import load_file, models_dir

    new = load_file(FR.write_model(tmp_path / "front_release.toml"))
    old = load_file(models_dir() / "front_release.toml")
    assert new.provenance.controllers == old.provenance.controllers
    assert (new.provenance.trials, new.provenance.seed) == (old.provenance.trials, old.provenance.seed)
    assert abs(new.provenance.attempts - old.provenance.attempts) <= 0.005 * old.provenance.attempts
    assert new.provenance.release_mean == pytest.approx(old.provenance.release_mean, abs=1e-6)
    assert new.provenance.release_std == pytest.approx(old.provenance.release_std, abs=1e-6)
    assert new.provenance.p_contact_later == pytest.approx(old.provenance.p_contact_later, abs=0.01)
    assert ks_2samp(np.ravel(new.map.release), np.ravel(old.map.release)).pvalue > 0.05
    assert ks_2samp(np.ravel(new.map.length), np.ravel(old.map.length)).pvalue > 0.05


@pytest.mark.slow
def test_identified_model_predicts_the_closed_loop_at_reduced_trials():
    # 48 closed-loop trials per controller (seed 0; the stored map came from seed 1). The loop's
    # converged-by-attempt fraction is binomial: SE = sqrt(p(1-p)/48) <= 7.2 points; the model's
    # 40000 draws add nothing noticeable. Every bin must lie within z SE (p from the model, floored
    # at 2/48 so a bin the model puts at 0 or 1 still allows one or two trials), z = 3.4 the
    # Bonferroni bound of a 5 % family-wise error over the 60 bins (6 controllers x 10 attempts; 3 SE
    # alone would fail one bin of a correct model in ~15 % of seeds), and the mean
    # attempts within 3 sd/sqrt(48). This is the statistical check at this trial count; the
    # 200-trial targets (0.3 attempts, 5 points) are benchmarks/bench_front_model.py's.
    n = 48
    res = FR.agreement(n, seed=0)
    for label, r in res.items():
        model = np.asarray(r["model"]["converged_by_attempt"])
        loop = np.asarray(r["loop"]["converged_by_attempt"])
        p = np.clip(model, 2 / n, 1 - 2 / n)
        tol = 3.4 * np.sqrt(p * (1 - p) / n)
        assert np.all(np.abs(model - loop) <= tol), (label, np.round(model - loop, 3), np.round(tol, 3))
        assert abs(r["mean_diff"]) <= 3 * r["mean_se"], (label, r["mean_diff"], r["mean_se"])
    # the paper's 0th-order plant misses where the identified map does not: the naive controllers
    # converge by chance in the loop (the release depends on the push), which i.i.d. N(300, 75²) cannot give
    for label in ("K_c=0, δ(0)=0",):
        r = res[label]
        paper = np.asarray(r["paper"]["converged_by_attempt"])
        loop = np.asarray(r["loop"]["converged_by_attempt"])
        model = np.asarray(r["model"]["converged_by_attempt"])
        assert np.max(np.abs(paper - loop)) > 2 * np.max(np.abs(model - loop))
