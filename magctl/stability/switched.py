"""Side pushing as the algorithm runs it: a switched piecewise-linear attempt map (paper §V-B, eq 16–18).

Eq 16 is a *distance*, ``D_s,des = |P_g − P_s|``, and every pass pushes the sphere towards
the goal from whichever side it now lies, so an over-push reverses the next pass. With a
linear plant ``D_s,act = ρ·(D_s,des + Δ)`` (``ρ`` = the model ratio of eq 19–20) and the
corrected eq 18, ``Δ(i+1) = Δ(i) − K_s(D_s,act − D_s,des)``, the state
``x = (|e|, Δ)`` (``|e| ≥ 0`` the distance to the goal) moves by one of three linear maps:

* **under-push** (the sphere stays on its side, ``(1 − ρ)|e| − ρΔ ≥ 0``)::

      A_u = [[1 − ρ, −ρ], [K_s(1 − ρ), 1 − K_s ρ]]    λ² − (2 − ρ(1 + K_s))λ + (1 − ρ)

  — the signed 1-D model's matrix (``magctl.stability.iteration.sweep(..., "full")``);
* **over-push** (the sphere crosses the goal; the next pass comes from the other side)::

      A_o = diag(−1, 1)·A_u = [[ρ − 1, ρ], [K_s(1 − ρ), 1 − K_s ρ]]    λ² − ρ(1 − K_s)λ + (ρ − 1)

* **no push** (``D_s,des + Δ ≤ 0``: eq 22 asks for an infinite gap, nothing moves)::

      A_0 = [[1, 0], [K_s, 1]]

The map ``F`` is continuous and positively homogeneous (``F(ax) = aF(x)``, ``a ≥ 0``), so
local and global stability coincide (without the bounds of §V-B step 1, which only limit
large errors) and convergence is exponential when it happens.

Verdicts, three ways:

* :func:`jsr_bounds` — joint spectral radius of the branches: an upper bound below 1 would prove
  stability under *any* switching. Here it never can: ``A_0`` has the double eigenvalue 1, and
  ``A_u`` alone is unstable wherever the signed model is (1.49 at ``K_s = 0.9, ρ = 1.4``). The
  bounds are reported to show how far arbitrary switching is from the state-dependent one;
* :func:`switched_verdict` — the state-dependent switching: the growth factor of ``|e|`` per
  attempt of the homogeneous map from 33 start directions (below 1: stable, 1: marginal), with an
  exact witness when a ray that the ``N``-attempt map returns to itself scaled by ``μ ≥ 1``
  exists (that start does not converge). A common quadratic Lyapunov function cannot certify
  the map: the no-push branch fixes the ray ``(0, Δ < 0)`` (at the goal, nothing moves), so no
  ``V`` decreases strictly there;
* :func:`switched_growth_rate` — the asymptotic growth factor per attempt of the map iterated
  from many directions (vectorised over gain and ratio grids, for the stable regions);
  :func:`map_growth_rate` measures the same number on the nonlinear attempt map
  :func:`magctl.stability.iteration.side_attempt_map` with a linear plant (eq 22 model against
  eq 22 scaled: ``D_s,act = ρ·(D_s,des + Δ)`` exactly).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from magctl.control.learning import LearningLaw
from magctl.control.side_models import ExpSideModel
from magctl.core.checks import check_positive
from magctl.core.errors import MagctlError
from magctl.core.units import UM
from magctl.stability.iteration import side_attempt_map

_T = np.diag([-1.0, 1.0])
UNDER, OVER, NO_PUSH = 0, 1, 2
BRANCH_NAMES = {UNDER: "under-push", OVER: "over-push", NO_PUSH: "no push"}


# --- the plant eq 22 scaled -------------------------------------------------------------------------
@dataclass(frozen=True)
class ScaledSideModel:
    """A side-push curve scaled from a base one: ``D_s(D_g) = scale·D_s,base(D_g / gap_scale)``.

    ``scale`` multiplies every displacement (eq 22 against itself scaled by ``s`` gives the
    linear plant ``D_s,act = s·(D_s,des + Δ)``: model ratio ``ρ = s``); ``gap_scale`` stretches
    the gap axis (a curve that decays ``gap_scale`` times more slowly, as a mismatched plant).
    """

    base: object = ExpSideModel()
    scale: float = 1.0
    gap_scale: float = 1.0
    name: str = "scaled"

    def __post_init__(self):
        check_positive("plant scale", self.scale)
        check_positive("plant gap scale", self.gap_scale)

    def displacement(self, dg):
        return self.scale * self.base.displacement(np.asarray(dg, dtype=float) / self.gap_scale)

    def gap(self, ds):
        return self.gap_scale * self.base.gap(np.asarray(ds, dtype=float) / self.scale)

    def slope(self, ds):
        return self.gap_scale * self.base.slope(np.asarray(ds, dtype=float) / self.scale) / self.scale


# --- the branches -----------------------------------------------------------------------------------
def branch_matrices(ks: float, ratio: float) -> dict[int, np.ndarray]:
    """``A_u``, ``A_o``, ``A_0`` of the module docstring (keys ``UNDER``, ``OVER``, ``NO_PUSH``)."""
    k, r = float(ks), float(ratio)
    a_u = np.array([[1.0 - r, -r], [k * (1.0 - r), 1.0 - k * r]])
    return {UNDER: a_u, OVER: _T @ a_u, NO_PUSH: np.array([[1.0, 0.0], [k, 1.0]])}


def switched_step(x, ks, ratio):
    """One attempt of the switched map, vectorised: ``x`` (..., 2) = ``(|e|, Δ)``; ``ks``, ``ratio`` broadcast.

    Returns the next state and the branch taken (``UNDER``, ``OVER``, ``NO_PUSH``).
    """
    x = np.asarray(x, dtype=float)
    k, r = np.asarray(ks, dtype=float), np.asarray(ratio, dtype=float)
    e, d = x[..., 0], x[..., 1]
    cmd = e + d  # D_s,des + Δ
    push = cmd > 0
    act = np.where(push, r * cmd, 0.0)  # D_s,act
    e_new = e - act
    d_new = d - k * (act - e)
    branch = np.where(~push, NO_PUSH, np.where(e_new >= 0, UNDER, OVER))
    return np.stack([np.abs(e_new), d_new], axis=-1), branch


def _unit(theta):
    return np.stack([np.cos(theta), np.sin(theta)], axis=-1)


# --- joint spectral radius (arbitrary switching) -----------------------------------------------------
def jsr_bounds(mats, depth: int = 8) -> tuple[float, float]:
    """Bounds on the joint spectral radius of ``mats`` from all products of length 1..``depth``.

    Lower: ``max ρ(Π)^{1/k}``; upper: ``min_k max ‖Π‖₂^{1/k}`` (Rota–Strang). An upper bound
    below 1 proves stability for every switching sequence.
    """
    mats = [np.asarray(m, dtype=float) for m in mats]
    lo, hi = 0.0, np.inf
    prods = [np.eye(mats[0].shape[0])]
    for k in range(1, depth + 1):
        prods = [m @ p for p in prods for m in mats]
        stack = np.array(prods)
        lo = max(lo, float(np.max(np.abs(np.linalg.eigvals(stack)))) ** (1.0 / k))
        hi = min(hi, float(np.max(np.linalg.norm(stack, 2, axis=(1, 2)))) ** (1.0 / k))
    return lo, hi


# --- cones of the N-attempt map --------------------------------------------------------------------
def _pattern(theta, ks, ratio, n):
    x = _unit(theta)
    code = np.zeros(np.shape(theta), dtype=np.int64)
    for _ in range(n):
        x, b = switched_step(x, ks, ratio)
        code = code * 3 + b
    return code


def _cones(ks, ratio, n, samples=4001):
    """Maximal angle intervals of ``(|e|, Δ)`` directions in ``[−π/2, π/2]`` on which the ``n``-attempt branch
    sequence is constant, with the product matrix; boundaries refined by bisection."""
    th = np.linspace(-np.pi / 2, np.pi / 2, samples)
    code = _pattern(th, ks, ratio, n)
    cuts = np.flatnonzero(np.diff(code) != 0)
    a, b, ca = th[cuts], th[cuts + 1], code[cuts]
    for _ in range(48):  # bisection of every boundary at once
        m = 0.5 * (a + b)
        same = _pattern(m, ks, ratio, n) == ca
        a, b = np.where(same, m, a), np.where(same, b, m)
    edges = [th[0], *(0.5 * (a + b)), th[-1]]
    mats = branch_matrices(ks, ratio)
    cones = []
    for (a, b), c in zip(itertools.pairwise(edges), [code[0], *code[cuts + 1]], strict=True):
        seq, prod = [], np.eye(2)
        for _ in range(n):
            seq.append(int(c % 3))
            c //= 3
        for br in reversed(seq):
            prod = mats[br] @ prod
        cones.append((float(a), float(b), prod, tuple(reversed(seq))))
    return cones


def _growing_ray(cones, ks, ratio, n, tol):
    """A ray mapped to itself by the ``n``-attempt map with multiplier ``μ ≥ 1 − tol``, checked by iterating it."""
    best = None
    for _a, _b, m, seq in cones:
        w, v = np.linalg.eig(m)
        for mu, vec in zip(w, v.T, strict=True):
            if abs(mu.imag) > 1e-12 or mu.real < 1 - tol:
                continue
            vec = np.real(vec)
            vec = vec if vec[0] >= 0 else -vec
            if vec[0] < 1e-9:  # |e| = 0: the goal is reached, not a divergence
                continue
            x = vec.copy()
            for _ in range(n):
                x, _b2 = switched_step(x, ks, ratio)
            if np.linalg.norm(x - mu.real * vec) < 1e-9 * max(1.0, mu.real) and (best is None or mu.real > best[0]):
                best = (float(mu.real), vec, tuple(BRANCH_NAMES[s] for s in seq))
    return best


@dataclass
class SwitchedVerdict:
    """Verdict of the switched side-push map at one ``(K_s, ρ)``.

    Attributes
    ----------
    verdict : {"stable", "marginal", "unstable"}
        From the growth factor of ``|e|`` per attempt (:func:`switched_growth_rate`, 33 start directions;
        the map is homogeneous, so the size of the start does not matter).
    growth_rate : float
    growing_ray : dict or None
        A ray with ``|e| > 0`` that the ``N``-attempt map returns to itself scaled by ``μ ≥ 1`` (an exact
        witness that some start does not converge): ``multiplier_per_attempt``, ``direction``, ``branches``.
    branch_poles : dict
        Eigenvalues of each branch matrix.
    jsr : (float, float)
        Joint-spectral-radius bounds of the three branches (arbitrary switching; conservative).
    """

    ks: float
    ratio: float
    verdict: str
    growth_rate: float
    growing_ray: dict | None
    branch_poles: dict
    jsr: tuple[float, float]


def switched_verdict(ks: float, ratio: float, *, ray_attempts: int = 6, margin: float = 1e-3) -> SwitchedVerdict:
    """Stability of the switched side-push map (module docstring) at one ``(K_s, ρ)``.

    From the growth factor of ``|e|`` per attempt, the largest over 33 start directions
    (:func:`switched_growth_rate`): ``stable`` below ``1 − margin``, ``unstable`` above ``1 + margin``,
    ``marginal`` between — e.g. for ``K_s ρ ≥ 2`` a no-push attempt followed by an over-push lands the
    sphere exactly as far past the goal, a neutral 2-cycle that attracts (eq 20's bound showing through).
    ``growing_ray`` reports a ray with ``|e| > 0`` that the ``N``-attempt map (``N ≤ ray_attempts``) returns
    scaled by ``μ ≥ 1``: an exact witness that *that* start does not converge. Where the verdict is
    ``stable`` such a ray is repelling (e.g. ``K_s = 0.7, ρ = 2.9``: a 2-cycle with ``μ = 1.007`` per
    attempt that no start on the 33-direction grid follows): almost every start converges.
    With ``K_s = 0`` the law is idle and ``Δ ≡ Δ(0) = 0``,
    so only the start ``Δ = 0`` exists: ``|e(i+1)| = |1 − ρ||e(i)|``.
    """
    ks, ratio = float(ks), float(ratio)
    if not (np.isfinite(ks) and np.isfinite(ratio) and ratio > 0):
        raise MagctlError(f"switched side map: K_s={ks!r} must be finite and the ratio {ratio!r} positive")
    mats = branch_matrices(ks, ratio)
    poles = {BRANCH_NAMES[b]: np.roots(np.poly(m)) for b, m in mats.items()}
    jsr = jsr_bounds(list(mats.values()), depth=6)
    if ks == 0:
        rate = abs(1.0 - ratio)
        verdict = "stable" if rate < 1 - margin else ("marginal" if rate <= 1 + margin else "unstable")
        return SwitchedVerdict(ks, ratio, verdict, rate, None, poles, jsr)
    rate = float(switched_growth_rate(ks, ratio, directions=33))
    ray = None
    for n in range(1, ray_attempts + 1):
        found = _growing_ray(_cones(ks, ratio, n), ks, ratio, n, 1e-9)
        if found is not None:
            ray = {"multiplier_per_attempt": found[0] ** (1.0 / n), "direction": found[1].tolist(),
                   "branches": found[2]}
            break
    verdict = "unstable" if rate > 1 + margin else ("stable" if rate < 1 - margin else "marginal")
    return SwitchedVerdict(ks, ratio, verdict, rate, ray, poles, jsr)


# --- growth rates ----------------------------------------------------------------------------------
def switched_growth_rate(ks, ratio, *, directions: int = 1, attempts: int = 400, window: int = 40) -> np.ndarray:
    """Growth factor per attempt of the goal distance ``|e|`` under the switched map (vectorised).

    ``ks`` and ``ratio`` broadcast to a grid. The starts are the task's ``(|e|, Δ) = (1, 0)``
    (``directions = 1``) or ``directions`` rays with ``|e| > 0`` (then the largest rate; a start
    with ``Δ ≤ −|e|`` and ``K_s = 0`` never moves: rate 1). The state is renormalised every attempt
    (the map is homogeneous) and the rate is the smaller of ``(max |e| over the last window / |e(0)|)^{1/(N − w)}``
    (a transient growth inflates it by only its factor to the power ``1/(N − w)``) and
    ``(max |e| over the last window / max |e| over the window ending at N/2)^{1/(N/2)}`` (a pause in the
    no-push branch with ``|e|`` already far below ``ε_p`` would hold this one at 1). Below 1: the sphere
    converges; 1: a neutral cycle.
    """
    k, r = np.broadcast_arrays(np.asarray(ks, dtype=float), np.asarray(ratio, dtype=float))
    th = np.array([0.0]) if directions == 1 else np.linspace(-np.pi / 2, np.pi / 2, directions + 2)[1:-1]
    x = np.broadcast_to(_unit(th), (*k.shape, th.size, 2)).copy()
    kk, rr = k[..., None], r[..., None]
    log_e0 = np.log(x[..., 0])
    logscale = np.zeros(log_e0.shape)
    top = np.full(log_e0.shape, -np.inf)
    mid = np.full(log_e0.shape, -np.inf)
    h = attempts // 2
    arrived = np.zeros(log_e0.shape, dtype=bool)
    with np.errstate(divide="ignore"):
        for i in range(attempts):
            x, _ = switched_step(x, kk, rr)
            arrived |= x[..., 0] <= 1e-12 * np.linalg.norm(x, axis=-1)  # exactly at the goal: the task stops
            n = np.linalg.norm(x, axis=-1)
            n = np.where(n > 0, n, 1e-300)
            logscale += np.log(n)
            x = x / n[..., None]
            log_e = np.log(np.maximum(x[..., 0], 1e-300)) + logscale
            if h - window <= i < h:
                mid = np.maximum(mid, log_e)
            if i >= attempts - window:
                top = np.maximum(top, log_e)
    # the envelope from the start (a transient growth inflates it by its factor^(1/N)) and between the two
    # windows (a pause with |e| already far below ε_p inflates that one): the smaller
    rate = np.exp(np.minimum(top - log_e0, (top - mid) * (attempts - window) / (attempts - h)) / (attempts - window))
    rate = np.where(arrived, 0.0, rate)
    return np.max(rate, axis=-1)


def map_growth_rate(ks, ratio, *, directions: int = 33, e0: float = 1e-9 * UM, attempts: int = 400,
                    window: int = 40) -> np.ndarray:
    """The growth factor of ``|e|`` measured on :func:`~magctl.stability.iteration.side_attempt_map` (vectorised).

    The map runs the algorithm itself — eq 16 distance, eq 17 gap from the eq 22 model, the plant's
    displacement towards the goal from whichever side, the corrected eq 18 law — with the plant eq 22
    scaled by ``ratio`` (``D_s,act = ρ(D_s,des + Δ)`` exactly), no tolerance stop and the §V-B bounds
    off (they only limit errors far larger than the ones the rate is measured on). Starts: ``|e| = e0
    cos θ``, ``Δ(0) = e0 sin θ`` for ``directions`` angles in ``(−π/2, π/2)`` (the law block's initial
    value), only ``Δ(0) = 0`` when ``K_s = 0`` (the law is idle). Rate as :func:`switched_growth_rate`,
    the largest over the starts; 0 for a start that lands exactly on the goal.
    """
    k, r = np.broadcast_arrays(np.asarray(ks, dtype=float), np.asarray(ratio, dtype=float))
    th = np.linspace(-np.pi / 2, np.pi / 2, directions + 2)[1:-1]
    flat_k, flat_r = k.ravel(), r.ravel()
    res = np.empty(flat_k.size)
    h = attempts // 2
    for rho in np.unique(flat_r):
        sel = np.flatnonzero(flat_r == rho)
        kk = np.repeat(flat_k[sel], th.size)
        tt = np.tile(th, sel.size)
        tt = np.where(kk == 0, 0.0, tt)
        law = LearningLaw("side_law", -kk, initial=e0 * np.sin(tt))
        with np.errstate(over="ignore", invalid="ignore"):
            run = side_attempt_map(kk, e0 * np.cos(tt), model="exp", plant=ScaledSideModel(scale=float(rho)),
                                   eps=0.0, max_attempts=attempts, min_gap=-np.inf, law=law)
        e = np.abs(run["error"])
        d = np.abs(np.c_[run["correction"], run["correction"][:, -1:]])
        with np.errstate(invalid="ignore"):
            arrived = np.any((e <= 1e-12 * np.hypot(e, d)) & np.isfinite(d), axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            log_e = np.log(np.maximum(e, 1e-300))
        top = log_e[:, -window:].max(axis=1)
        mid = log_e[:, h - window + 1:h + 1].max(axis=1)
        rate = np.exp(np.minimum(top - log_e[:, 0], (top - mid) * (attempts - window) / (attempts - h))
                      / (attempts - window))
        rate = np.where(arrived, 0.0, np.where(np.all(np.isfinite(e), axis=1), rate, np.inf))
        res[sel] = rate.reshape(sel.size, th.size).max(axis=1)
    return res.reshape(k.shape)


def switched_stable(ks, ratio, *, margin: float = 1e-3, directions: int = 33) -> np.ndarray:
    """Vectorised stable/not-stable of the switched map on a ``(K_s, ρ)`` grid (broadcast).

    Stable when the growth factor of ``|e|`` from ``directions`` starts is below ``1 − margin``
    (a neutral 2-cycle gives 1); for ``K_s = 0`` only ``Δ = 0`` exists: ``|1 − ρ| < 1 − margin``.
    Agrees with :func:`switched_verdict` (which also looks for an invariant ray) on the grids of the tests.
    """
    k, r = np.broadcast_arrays(np.asarray(ks, dtype=float), np.asarray(ratio, dtype=float))
    rate = switched_growth_rate(k, r, directions=directions)
    rate = np.where(k == 0, np.abs(1.0 - r), rate)
    return rate < 1 - margin


def switched_gain_ranges(ratio: float, gains=None) -> list[tuple[float, float]]:
    """Runs of stable ``K_s`` (grid ends) at ``ratio``; ``gains`` default 0..4 by 0.02.

    ``K_s = 0`` is its own case (the law is idle): very small ``K_s`` leave ``Δ`` nearly frozen after a
    no-push attempt and count as marginal, so it often forms a run of one.
    """
    gains = np.round(np.arange(0.0, 4.0001, 0.02), 10) if gains is None else np.asarray(gains, dtype=float)
    ok = switched_stable(gains, float(ratio))
    runs, start = [], None
    for i, flag in enumerate([*ok.tolist(), False]):
        if flag and start is None:
            start = i
        elif not flag and start is not None:
            runs.append((float(gains[start]), float(gains[i - 1])))
            start = None
    return runs


def boundary(ratios, stable) -> float | None:
    """The first ratio of an increasing grid at which ``stable`` turns False (None if it never does)."""
    stable = np.asarray(stable, dtype=bool)
    bad = np.flatnonzero(~stable)
    return None if bad.size == 0 else float(np.asarray(ratios)[bad[0]])


__all__ = [
    "BRANCH_NAMES", "NO_PUSH", "OVER", "UNDER", "ScaledSideModel", "SwitchedVerdict", "boundary", "branch_matrices",
    "jsr_bounds", "map_growth_rate", "switched_gain_ranges", "switched_growth_rate", "switched_stable",
    "switched_step", "switched_verdict",
]
