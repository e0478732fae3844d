"""The paper's claims judged at the paper's own sample size (its §VI: ten trials per controller).

magctl runs hundreds of trials per controller; the paper ran ten. A claim magctl's large sample does not
bear out may still be what ten trials of magctl's plant would show. For each claim this module gives the
probability of the paper's observation under magctl's model at ``n`` = 10:

* a share the paper saw in all ten trials (``p_all``: ``q¹⁰`` for magctl's per-trial share ``q``) or in
  none (``p_none``: ``(1 − q)¹⁰``), binomial;
* an ordering of two controllers' mean attempts (``p_order``): the share of bootstrap pairs of ten-trial
  samples, drawn from magctl's per-trial attempts of each, whose means come out in the paper's order.

The verdict rule (:func:`verdict`, stated in every report by :data:`RULE`): **reproduced** when
magctl's large sample says what the paper says; otherwise, for a share, **consistent at n = 10** when
the paper's observation has probability ≥ :data:`ALPHA` under magctl's model, and for an ordering
**not resolvable** when ten-trial samples give the paper's order with probability ≥ :data:`ALPHA`
(two such controllers cannot be ranked from ten trials each); else **not reproduced** (or
**opposite** when magctl finds the reverse).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

PAPER_TRIALS = 10
"""Trials per controller in the paper's §VI experiments."""
ALPHA = 0.05
"""Smallest probability of the paper's observation under magctl's model that still counts as consistent."""
RULE = (f"Verdicts: reproduced — magctl's large sample says what the paper says; consistent at n = "
        f"{PAPER_TRIALS} — it does not, but the paper's observation (a share seen in all or none of its "
        f"{PAPER_TRIALS} trials) has probability ≥ {ALPHA:.0%} under magctl's model (binomial); not resolvable — "
        f"an ordering of two controllers that {PAPER_TRIALS}-trial samples of magctl's plant give in the paper's "
        f"direction with probability ≥ {ALPHA:.0%} (bootstrap); not reproduced / opposite — otherwise. "
        "Causes: each is built from the numbers it cites and printed only where its own check of those numbers "
        "holds in this run; otherwise the row says \"unexplained\" and shows what was checked.")


@dataclass(frozen=True)
class Cause:
    """Why a claim is not reproduced: a sentence built from the numbers it cites, and the check of those
    numbers that makes the sentence true in this run (``holds``).

    A cause whose check fails is not printed as an explanation: :meth:`text` then reports the claim as
    unexplained and shows what was checked, so a report can never carry an explanation its own numbers
    contradict.
    """

    sentence: str
    holds: bool

    def text(self) -> str:
        if self.holds:
            return self.sentence
        return f"{UNEXPLAINED} the computed cause does not hold in this run ({self.sentence})"


UNEXPLAINED = "unexplained:"
"""How a claim's cause starts when its own check fails (:class:`Cause`)."""


def _share(q: float) -> float:
    q = float(q)
    if not 0.0 <= q <= 1.0:
        raise ValueError(f"a share must lie in [0, 1], got {q!r}")
    return q


def p_all(q: float, n: int = PAPER_TRIALS) -> float:
    """Probability that all ``n`` trials show an outcome each shows with probability ``q``: ``qⁿ``."""
    return _share(q) ** n


def p_none(q: float, n: int = PAPER_TRIALS) -> float:
    """Probability that none of ``n`` trials shows an outcome each shows with probability ``q``: ``(1 − q)ⁿ``."""
    return (1.0 - _share(q)) ** n


def p_at_least(k: int, q: float, n: int = PAPER_TRIALS) -> float:
    """Probability that at least ``k`` of ``n`` trials show an outcome each shows with probability ``q``."""
    from scipy.stats import binom  # here: the claims' rows (magctl.studies.runner) need this module, not scipy

    return float(binom.sf(k - 1, n, _share(q)))


def p_order(a, b, n: int = PAPER_TRIALS, draws: int = 20000, seed: int = 0) -> float:
    """Probability that the mean of ``n`` trials drawn from ``a`` is below that of ``n`` drawn from ``b``
    (ties count half): a bootstrap over magctl's per-trial attempts of the two controllers."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    if a.size == 0 or b.size == 0:
        raise ValueError("p_order needs per-trial values of both controllers")
    rng = np.random.default_rng(seed)
    ma = rng.choice(a, size=(draws, n)).mean(axis=1)
    mb = rng.choice(b, size=(draws, n)).mean(axis=1)
    return float(np.mean(ma < mb) + 0.5 * np.mean(ma == mb))


def verdict(holds: bool, p_paper: float | None, *, ordering: bool = False, opposite: bool = False) -> str:
    """The verdict of :data:`RULE` for a claim whose large-sample test ``holds`` and whose observation has
    probability ``p_paper`` at the paper's ten trials (None: not a ten-trial observation)."""
    if holds:
        return "reproduced"
    if p_paper is not None and p_paper >= ALPHA:
        return "not resolvable" if ordering else f"consistent at n = {PAPER_TRIALS}"
    return "opposite" if opposite else "not reproduced"


def mean_difference(a, b) -> tuple[float, float]:
    """Difference of the mean attempts of two controllers' trials and its standard error."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(a.mean() - b.mean()), float(np.sqrt(a.var(ddof=1) / a.size + b.var(ddof=1) / b.size))


def ordering_cause(faster: str, slower: str, trials: dict) -> Cause:
    """Why the paper's ``faster`` controller does not beat ``slower`` here: the two are indistinguishable
    (mean difference within twice its standard error), or the order is reversed beyond it."""
    d, se = mean_difference(trials[faster], trials[slower])
    n = len(trials[faster])
    if abs(d) <= 2 * se:
        return Cause(f"{faster} and {slower} differ by {d:+.1f} mean attempts over {n} trials, within twice its "
                     f"standard error ({2 * se:.1f}).", True)
    return Cause(f"over {n} trials {slower} is faster than {faster} by {d:.1f} ± {se:.1f} mean attempts (± standard "
                 "error): on magctl's plant the order is the reverse of the paper's.", d > 0)
