"""The front push's release map identified from the closed loop (models/front_release.toml)."""

from __future__ import annotations

import numpy as np
import pytest

from magctl.core.errors import MagctlError
from magctl.stability import iteration as S
from magctl.studies import front_release as FR


def test_paper_plant_is_the_one_bin_special_case():
    # A map whose release is N(300, 75²) at every push length, no lateral error, no coupling, must
    # give the paper's eq 14 distribution (the Markov chain of front_attempts_markov).
    from scipy.special import ndtri

    levels = np.linspace(0, 1, 401)
    q = 300e-6 + 75e-6 * ndtri(np.clip(levels, 1e-6, 1 - 1e-6))
    tab = S.ReleaseTable(np.array([1.0]), np.array([0.0, 2.0]), np.ones(2), np.tile(q, (2, 1)),
                         np.tile(q, (2, 1)), np.zeros((2, levels.size)))
    rmap = S.ReleaseMap(levels, tab, tab)
    for kc in (0.5, 1.0):
        ident = S.front_attempts_identified(kc, 0.0, 40000, release_map=rmap)
        markov = S.front_attempts_markov(kc, 0.0)
        # 40000 draws: binomial SE ≤ 0.0025 per bin; 0.012 is ~5 SE plus the tails cut at 1e-6
        assert np.max(np.abs(np.cumsum(ident[:-1]) - np.cumsum(markov[:-1]))) < 0.012


def test_release_map_rejects_bad_tables():
    levels = np.linspace(0, 1, 5)
    good = np.zeros((2, 5))
    with pytest.raises(MagctlError, match="shape"):
        S.ReleaseTable(np.array([1.0]), np.array([0.0, 2.0]), np.ones(2), np.zeros((2, 4)), good, good)
    with pytest.raises(MagctlError, match="increasing"):
        S.ReleaseTable(np.array([1.0]), np.array([2.0, 0.0]), np.ones(2), good, good, good)
    tab = S.ReleaseTable(np.array([1.0]), np.array([0.0, 2.0]), np.ones(2), good, good, good)
    with pytest.raises(MagctlError, match="levels"):
        S.ReleaseMap(levels[::-1], tab, tab)


def test_stored_map_loads_with_its_provenance():
    rmap = S.ReleaseMap.load()
    assert "identify_from_loop(trials=200, seed=1)" in rmap.source
    # first attempts: the sphere always touched (it is pushed 750 µm from rest)
    assert np.all(rmap.first.p_contact > 0.95)
    # from attempt 2 the shortest pushes end without contact: the flow moved the sphere into eq 11's band
    assert rmap.later.p_contact[0] < 0.1 < 0.9 < rmap.later.p_contact[-1]


@pytest.mark.slow
def test_regenerating_the_map_gives_the_stored_numbers(tmp_path):
    path = FR.write_model(tmp_path / "front_release.toml")
    from magctl.config import models_dir

    assert path.read_text() == (models_dir() / "front_release.toml").read_text()
