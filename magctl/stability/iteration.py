"""Iteration-domain stability of the push loops (paper §V-A and §V-B).

Time is the push attempt (``dt = 1``). The learning laws are the blocks of
:mod:`magctl.control.learning`; their ``to_control()`` integrators are what the
transfer functions below are built from.

* Front pushing (eq 13–15): ``G_ol = K_c/(z − 1)``, ``G_cl = K_c/(z − 1 + K_c)``.
* Side pushing as the paper analyses it (eq 19–20): ``H_ol = K_s ρ/(z − 1)`` with the
  model ratio ``ρ = F_lin·F_act⁻¹`` taken constant.
* Side pushing with the feed-forward path (eq 16–17) kept: the sphere position is a
  second state, ``e(i+1) = e − ρ(e + Δ)``, ``Δ(i+1) = Δ − K_s(ρ(e + Δ) − e)``, whose
  characteristic polynomial is ``z² − (2 − ρ(1 + K_s)) z + (1 − ρ)``.
* The nonlinear attempt map with the plant ``F_act`` = eq 22, the model eq 22 or 23,
  the minimum-gap bound and the bounded ``D_s,des`` (§V-B step 1).
* Stochastic convergence of front pushing with a random release ``D_p,r``: a Markov
  chain on the compensation ``δ`` and the matching Monte Carlo of the attempt map.
* Front pushing with the release map identified from the closed loop
  (``models/front_release.toml``, :class:`ReleaseMap`): the release depends on the push length
  and the previous release, with the sphere's distance off the line and contact drawn with it.

Lengths are metres inside. What ``magctl stability front|side`` prints of these analyses (µm in unit-suffixed
keys) is gathered by :mod:`magctl.cli.stability_reports`.
"""

from __future__ import annotations

from dataclasses import dataclass

import control
import numpy as np
from scipy.special import ndtr

from magctl.config import load_model
from magctl.control.curve_learning import CurveLearningLaw
from magctl.control.learning import ATTEMPT, LearningLaw, front_push_law, side_push_law
from magctl.control.push_params import goal_distance, task_defaults
from magctl.control.release_model import ReleaseMap
from magctl.control.side_models import ExpSideModel, LinSideModel, TabulatedSideModel, side_model
from magctl.core.diagram import Diagram
from magctl.core.errors import MagctlError
from magctl.core.linear import Gain, Integrator, Sum
from magctl.core.units import UM

POLE_TOL = 1e-9

# The push tasks' own parameters (models/push.toml, sources there): the analysis studies the loop the
# tasks run.
_PUSH = load_model("push")
_FRONT, _SIDE = task_defaults("front"), task_defaults("side")
FRONT_EPS = _FRONT["eps"]  # ε_p of eq 12 (§VI-A)
FRONT_MAX_ATTEMPTS = _FRONT["max_attempts"]
RELEASE_MEAN = _PUSH.release.mean  # D_p,r measured, 300 ± 75 µm over five trials (§IV-D)
RELEASE_STD = _PUSH.release.std
RELEASE_MODEL = _PUSH.release.model  # simulated D_p,r (§IV-D), the model-based δ(0)
SIDE_EPS = _SIDE["eps"]  # one pixel (§VI-B)
SIDE_MAX_ATTEMPTS = _SIDE["max_attempts"]
SIDE_GOAL = goal_distance("side")
MIN_GAP = _SIDE["min_gap"]  # contact threshold of Fig 6 (§IV-D)


# --- classification ------------------------------------------------------------------------------
def classify(poles, tol: float = POLE_TOL) -> tuple[str, str]:
    """Stability verdict and damping class of a discrete system from its poles.

    Returns
    -------
    verdict : {"stable", "marginal", "unstable"}
        All poles strictly inside the unit circle, some on it, some outside.
    damping : str
        For stable loops: ``"critically damped"`` (every pole at the origin: dead-beat,
        the paper's name for ``K_c = 1``), ``"overdamped"`` (dominant pole real and
        positive: monotone approach), ``"underdamped"`` (dominant pole negative or
        complex: the error changes sign, over-push). Marginal loops are ``"oscillatory"``
        (a pole at −1 or a complex pair on the circle: sustained oscillation) or
        ``"integrating"`` (pole at +1: the error is never corrected). Unstable loops
        are ``"unstable"``.
    """
    p = np.atleast_1d(np.asarray(poles, dtype=complex))
    if p.size == 0:
        return "stable", "critically damped"
    mag = np.abs(p)
    rho = mag.max()
    if rho > 1 + tol:
        return "unstable", "unstable"
    if rho >= 1 - tol:
        on = p[mag >= 1 - tol]
        if np.all(np.abs(on - 1) < 1e-6):
            return "marginal", "integrating"
        return "marginal", "oscillatory"
    if rho < 1e-6:
        return "stable", "critically damped"
    dom = p[mag >= rho - 1e-9]
    if np.all(np.abs(dom.imag) < 1e-9) and np.all(dom.real > 0):
        return "stable", "overdamped"
    return "stable", "underdamped"


@dataclass
class LoopAnalysis:
    """A loop's transfer functions, poles and verdict.

    Attributes
    ----------
    open_loop, closed_loop : control.TransferFunction
        ``dt = 1`` attempt.
    poles : ndarray of complex
        Closed-loop poles.
    verdict, damping : str
        See :func:`classify`.
    stable_gain_range : tuple of float
        Open interval of the gain over which the loop is stable (at the given ratio).
    """

    gain: float
    ratio: float
    open_loop: control.TransferFunction
    closed_loop: control.TransferFunction
    poles: np.ndarray
    verdict: str
    damping: str
    stable_gain_range: tuple[float, float]


def _loop(law: LearningLaw, ratio: float, sign: float, gain: float, gain_range) -> LoopAnalysis:
    # the law's integrator g/(z−1); sign turns −K_s into the paper's +K_s convention
    ol_ss = law.to_control() * (sign * ratio)
    cl_ss = control.feedback(ol_ss, 1)
    # poles from the state space: a transfer function would cancel the pole at 1 when the gain is 0
    poles = np.asarray(cl_ss.poles(), dtype=complex)
    ol, cl = control.tf(ol_ss), control.tf(cl_ss)
    verdict, damping = classify(poles)
    return LoopAnalysis(gain, ratio, ol, cl, poles, verdict, damping, gain_range)


def front_loop(kc: float) -> LoopAnalysis:
    """Eq 14–15 from the eq 13 law block: ``G_cl = K_c/(z − 1 + K_c)``, stable for ``0 < K_c < 2``."""
    return _loop(front_push_law(kc), 1.0, 1.0, float(kc), (0.0, 2.0))


def side_loop(ks: float, ratio: float = 1.0) -> LoopAnalysis:
    """Eq 19–20 from the eq 18 law block with the model ratio ``ρ = F_lin·F_act⁻¹`` held constant.

    Stable for ``0 < K_s ρ < 2``, i.e. ``0 < K_s < 2/ρ`` for ``ρ > 0``.
    """
    ratio = float(ratio)
    if not np.isfinite(ratio) or ratio == 0:
        raise MagctlError(f"model ratio {ratio!r} must be finite and non-zero")
    rng = (0.0, 2.0 / ratio) if ratio > 0 else (2.0 / ratio, 0.0)
    return _loop(side_push_law(ks), ratio, -1.0, float(ks), rng)


# --- iteration-domain diagrams (the law blocks wired with a linear plant) -----------------------
def front_iteration_diagram(law: LearningLaw) -> Diagram:
    """Eq 10–13 over attempts: ``P_s = P_g + δ − D_p,r``, ``e = P_g − P_s`` feeds the law.

    Inputs ``goal`` (``P_g``) and ``release`` (``D_p,r``); outputs ``sphere`` (``P_s``),
    ``error`` and ``delta``. ``Diagram.to_control()`` has the single pole ``1 − K_c``.
    """
    goal = Gain("goal", 1.0, in_unit="m", dt=ATTEMPT)
    sphere = Sum("sphere", "++-", unit="m", dt=ATTEMPT)
    err = Sum("error", "+-", unit="m", dt=ATTEMPT)
    return Diagram(
        "front_iterations",
        [law, goal, sphere, err],
        [("goal.y", "sphere.u0"), ("goal.y", "error.u0"), (f"{law.name}.y", "sphere.u1"), ("sphere.y", "error.u1"),
         ("error.y", f"{law.name}.e")],
        inputs={"goal": "goal.u", "release": "sphere.u2"},
        outputs={"sphere": "sphere.y", "error": "error.y", "delta": f"{law.name}.y"},
        dt=ATTEMPT,
    )


def side_iteration_diagram(law: LearningLaw, ratio: float) -> Diagram:
    """Eq 16–18 over attempts with the plant linearised to ``D_s,act = ρ·(D_s,des + Δ)``.

    The sphere position is an integrator of the displacements; inputs ``goal``;
    outputs ``sphere``, ``error`` (``D_s,des``) and ``correction`` (``Δ``).
    """
    pos = Integrator("sphere", gain=1.0, in_unit="m", out_unit="m", dt=ATTEMPT)
    des = Sum("desired", "+-", unit="m", dt=ATTEMPT)
    cmd = Sum("command", "++", unit="m", dt=ATTEMPT)
    plant = Gain("plant", float(ratio), in_unit="m", dt=ATTEMPT)
    lerr = Sum("law_error", "+-", unit="m", dt=ATTEMPT)
    return Diagram(
        "side_iterations",
        [law, pos, des, cmd, plant, lerr],
        [
            ("sphere.y", "desired.u1"), ("desired.y", "command.u0"), (f"{law.name}.y", "command.u1"),
            ("command.y", "plant.u"), ("plant.y", "sphere.u"), ("plant.y", "law_error.u0"),
            ("desired.y", "law_error.u1"), ("law_error.y", f"{law.name}.e"),
        ],
        inputs={"goal": "desired.u0"},
        outputs={"sphere": "sphere.y", "error": "desired.y", "correction": f"{law.name}.y"},
        dt=ATTEMPT,
    )


def side_full_poles(ks: float, ratio: float) -> np.ndarray:
    """Poles of the side loop with its feed-forward path, from the diagram via python-control."""
    sys = side_iteration_diagram(side_push_law(ks), ratio).to_control()
    return np.asarray(control.poles(sys), dtype=complex)


def side_full_stable_range(ratio: float) -> tuple[float, float] | None:
    """``K_s`` interval where the two-state side loop is stable (Jury): ``0 < K_s < 4/ρ − 2`` for ``0 < ρ < 2``."""
    if not 0 < ratio < 2:
        return None
    return (0.0, 4.0 / ratio - 2.0)


# --- vectorised (gain, ratio) sweeps -------------------------------------------------------------
def sweep(gains, ratios, loop: str = "paper") -> dict[str, np.ndarray]:
    """Stability verdicts on the grid ``gains × ratios`` (rows: gains).

    ``loop="paper"``: pole ``1 − Kρ`` (eq 15/20). ``loop="full"``: roots of
    ``z² − (2 − ρ(1 + K))z + (1 − ρ)`` (side loop with its feed-forward path).
    Returns ``stable`` (bool) and ``spectral_radius`` arrays shaped ``(len(gains), len(ratios))``.
    """
    k = np.asarray(gains, dtype=float)[:, None]
    r = np.asarray(ratios, dtype=float)[None, :]
    if loop == "paper":
        radius = np.abs(1.0 - k * r)
    elif loop == "full":
        tr = 2.0 - r * (1.0 + k)
        det = 1.0 - r
        disc = np.sqrt((tr * tr - 4.0 * det).astype(complex))
        radius = np.maximum(np.abs(0.5 * (tr + disc)), np.abs(0.5 * (tr - disc)))
    else:
        raise MagctlError(f"sweep loop {loop!r} is not known; use 'paper' or 'full'")
    return {"stable": radius < 1.0 - POLE_TOL, "spectral_radius": radius}


# --- front pushing: attempt map and convergence distribution -------------------------------------
def front_attempt_map(kc, delta0, release: np.ndarray, *, eps: float = FRONT_EPS, overshoot: float = 0.0,
                      law: LearningLaw | None = None) -> dict[str, np.ndarray]:
    """Attempt-by-attempt front pushing (eq 10–13), vectorised over trials.

    Attempt ``i`` leaves the sphere at ``P_s = P_g + δ(i) + overshoot − D_p,r(i)`` (pushed to
    ``P_o`` of eq 10, over-pushed by the servo, then pulled back on retraction); the task
    stops when ``|P_g − P_s| < ε_p`` (eq 12), else eq 13 updates ``δ``.

    Parameters
    ----------
    release : (B, N) array
        ``D_p,r`` of each trial's ``N`` attempts (m); ``N`` is the attempt limit.

    Returns
    -------
    dict with ``attempts`` (B,) int (attempts used; −1 = not converged within N) and
    ``error`` (B, N) ``P_g − P_s`` after each attempt (NaN after convergence).
    """
    release = np.atleast_2d(np.asarray(release, dtype=float))
    b, n = release.shape
    law = law or front_push_law(kc, delta0)
    st = law.initial_state(b)
    done = np.zeros(b, dtype=bool)
    attempts = np.full(b, -1)
    err = np.full((b, n), np.nan)
    for i in range(n):
        e = release[:, i] - overshoot - law.output(st, {})["y"]
        err[:, i] = np.where(done, np.nan, e)
        hit = ~done & (np.abs(e) < eps)
        attempts[hit] = i + 1
        done |= hit
        st = law.update_where(st, {"e": e}, ~done)
    return {"attempts": attempts, "error": err}


def front_attempts_markov(kc: float, delta0: float, *, mean: float = RELEASE_MEAN, std: float = RELEASE_STD,
                          eps: float = FRONT_EPS, max_attempts: int = FRONT_MAX_ATTEMPTS, overshoot: float = 0.0,
                          n_grid: int = 1201, n_quad: int = 801) -> np.ndarray:
    """Probability of converging at each attempt, with ``D_p,r ~ N(mean, std²)`` i.i.d.

    A Markov chain on the compensation ``δ``: from ``δ`` an attempt converges with
    probability ``P(|D_p,r − overshoot − δ| < ε_p)``; otherwise ``δ`` moves to
    ``δ + K_c(D_p,r − overshoot − δ)`` (eq 13). The density of ``δ`` lives on a grid
    (linear interpolation) and ``D_p,r`` on a quadrature grid over ±6σ.

    Returns
    -------
    ndarray, shape (max_attempts + 1,)
        ``p[i-1]`` = P(converged at attempt i) for i = 1…N; ``p[-1]`` = P(not converged).
    """
    kc = float(kc)
    c = mean - overshoot
    d = np.linspace(c - 6 * std, c + 6 * std, n_quad)
    w = np.exp(-0.5 * ((d - c) / std) ** 2)
    w /= w.sum()
    half = max(abs(delta0 - c), 6 * std) * (1.0 + abs(kc - 1.0)) + 6 * std
    grid = np.linspace(c - half, c + half, n_grid)
    h = grid[1] - grid[0]
    mass = np.zeros(n_grid)
    _deposit(mass, np.array([delta0]), np.array([1.0]), grid[0], h)
    conv_mask = np.abs(d[None, :] - grid[:, None]) < eps  # (grid, quad)
    # exact convergence probability; the quadrature only carries the surviving mass
    p_conv = ndtr((grid + eps - c) / std) - ndtr((grid - eps - c) / std)
    w_stay = w[None, :] * ~conv_mask
    w_stay *= ((1.0 - p_conv) / np.maximum(w_stay.sum(axis=1), 1e-300))[:, None]
    new_delta = grid[:, None] + kc * (d[None, :] - grid[:, None])
    out = np.zeros(max_attempts + 1)
    for i in range(max_attempts):
        out[i] = mass @ p_conv
        stay = mass[:, None] * w_stay
        nxt = np.zeros(n_grid)
        _deposit(nxt, new_delta.ravel(), stay.ravel(), grid[0], h)
        mass = nxt
    out[-1] = max(0.0, 1.0 - out[:-1].sum())
    return out


def _deposit(target: np.ndarray, x: np.ndarray, m: np.ndarray, x0: float, h: float) -> None:
    """Add masses ``m`` at positions ``x`` to a uniform grid by linear interpolation (clamped)."""
    n = target.size
    f = np.clip((x - x0) / h, 0.0, n - 1.0)
    i0 = np.minimum(np.floor(f).astype(int), n - 2)
    t = f - i0
    target += np.bincount(i0, m * (1 - t), minlength=n) + np.bincount(i0 + 1, m * t, minlength=n)


def front_attempts_monte_carlo(kc: float, delta0: float, trials: int = 20000, *, mean: float = RELEASE_MEAN,
                               std: float = RELEASE_STD, eps: float = FRONT_EPS,
                               max_attempts: int = FRONT_MAX_ATTEMPTS, overshoot: float = 0.0,
                               seed: int = 0) -> np.ndarray:
    """Same distribution as :func:`front_attempts_markov` from ``trials`` runs of the attempt map."""
    release = np.random.default_rng(seed).normal(mean, std, size=(trials, max_attempts))
    att = front_attempt_map(kc, delta0, release, eps=eps, overshoot=overshoot)["attempts"]
    out = np.bincount(np.where(att > 0, att - 1, max_attempts), minlength=max_attempts + 1)
    return out / trials


# --- front pushing: the release map identified from the closed loop ------------------------------
FRONT_GOAL = goal_distance("front")


def front_identified_map(kc, delta0, trials: int = 20000, *, release_map: ReleaseMap | None = None,
                         eps: float = FRONT_EPS, max_attempts: int = FRONT_MAX_ATTEMPTS, goal: float = FRONT_GOAL,
                         seed: int = 0, law: LearningLaw | None = None) -> dict[str, np.ndarray]:
    """Front pushing (eq 10–13) with the release map identified from the closed loop, vectorised over trials.

    Attempt ``i`` starts ``d`` from the goal (``d(0)`` = ``goal``) and aims along the line to it;
    the push length is ``L = d + δ(i)``; ``(R, lateral, contact)`` are drawn from ``release_map`` at
    ``L`` and the trial's previous release; the error along the line is ``e = R − δ(i)`` (fed to
    eq 13) and the distance to the goal ``d = √(e² + lateral²)`` (eq 12 tests ``d < ε_p``, as the
    task does).

    Returns ``attempts`` (B,) (−1 = not converged), ``error`` (B, N) signed along-line error,
    ``distance`` (B, N) and ``contact`` (B, N) (NaN / False after convergence).
    """
    rmap = release_map or ReleaseMap.load()
    rng = np.random.default_rng(seed)
    law = law or front_push_law(kc, delta0)
    st = law.initial_state(trials)
    d = np.full(trials, float(goal))
    done = np.zeros(trials, dtype=bool)
    attempts = np.full(trials, -1)
    err, dist = np.full((trials, max_attempts), np.nan), np.full((trials, max_attempts), np.nan)
    touched = np.zeros((trials, max_attempts), dtype=bool)
    last = np.zeros(trials)
    for i in range(max_attempts):
        delta = law.output(st, {})["y"]
        release, lateral, contact = rmap.sample(d + delta, i == 0, rng, last)
        last = np.where(done, last, release)
        e = release - delta
        d = np.where(done, d, np.hypot(e, lateral))
        err[:, i] = np.where(done, np.nan, e)
        dist[:, i] = np.where(done, np.nan, d)
        touched[:, i] = ~done & contact
        hit = ~done & (d < eps)
        attempts[hit] = i + 1
        done |= hit
        st = law.update_where(st, {"e": e}, ~done)
    return {"attempts": attempts, "error": err, "distance": dist, "contact": touched}


def front_attempts_identified(kc: float, delta0: float, trials: int = 20000, *, release_map: ReleaseMap | None = None,
                              max_attempts: int = FRONT_MAX_ATTEMPTS, seed: int = 0) -> np.ndarray:
    """P(converged at attempt i), i = 1…N, and P(not converged) last, from :func:`front_identified_map`."""
    att = front_identified_map(kc, delta0, trials, release_map=release_map, max_attempts=max_attempts,
                               seed=seed)["attempts"]
    return np.bincount(np.where(att > 0, att - 1, max_attempts), minlength=max_attempts + 1) / trials


# --- side pushing: nonlinear attempt map ---------------------------------------------------------
def side_attempt_map(ks, e0, *, model="lin", plant=None, min_gap: float = MIN_GAP, eps: float = SIDE_EPS,
                     max_attempts: int = SIDE_MAX_ATTEMPTS, printed_sign: bool = False, noise_rel: float = 0.0,
                     fixed_gap: float | None = None, seed: int = 0, mobility_rel: float = 0.0,
                     law: LearningLaw | CurveLearningLaw | None = None) -> dict[str, np.ndarray]:
    """Attempt-by-attempt side pushing (eq 16–18), vectorised over trials.

    Each attempt: ``D_s,des = min(|e|, D_max)`` with ``D_max = F_model⁻¹(min_gap)`` (eq 16,
    bounded as §V-B step 1 says); gap ``D_g = max(F_model(D_s,des + Δ), min_gap)`` (eq 17);
    the sphere moves ``D_s,act = m·F_act⁻¹(D_g)·max(0, 1 + noise_rel·N(0,1))`` along the
    direction it was pushed (towards the goal, from whichever side it now lies), with a
    per-trial mobility ``m = max(0, 1 + mobility_rel·N(0,1))``; ``Δ`` updates by eq 18
    (sign as corrected unless ``printed_sign``). A trial stops once ``|e| < ε_p`` (eq 12).

    With ``law`` a :class:`~magctl.control.curve_learning.CurveLearningLaw` the attempt is the
    curve-learning one of ``SidePushTask(learning="curve")``: ``D_s,des`` bounded by the
    estimate at ``min_gap``, the gap from the estimate's inverse, the law fed ``(D_g, D_s,act)``.

    Parameters
    ----------
    ks : float or (B,) array
        ``K_s`` (per trial for gain sweeps).
    e0 : float or (B,) array
        Initial goal distance ``|P_g − P_s|`` (m).
    model, plant : "lin", "exp" or a model object
        ``F`` used by the controller (eq 23 or 22) and the actual ``F_act`` (default eq 22).
    fixed_gap : float, optional
        The paper's naive controllers: every pass at this gap (370 or 500 µm), no model.

    Returns
    -------
    dict with ``attempts`` (B,) (attempts used; −1 = not converged), ``error`` (B, N+1)
    signed goal distance initially and after each attempt (NaN once finished), ``gap``
    (B, N) and ``correction`` (B, N) (``Δ`` used in each attempt).
    """
    model = side_model(model) if isinstance(model, str) else model
    plant = ExpSideModel() if plant is None else (side_model(plant) if isinstance(plant, str) else plant)
    ks = np.asarray(ks, dtype=float)
    e = np.asarray(e0, dtype=float)
    b = int(np.broadcast_shapes(ks.shape, e.shape, (1,))[0])
    e = np.broadcast_to(e, (b,)).astype(float)
    law = law or side_push_law(np.broadcast_to(ks, (b,)) if ks.ndim else float(ks), printed_sign=printed_sign)
    st = law.initial_state(b)
    rng = np.random.default_rng(seed)
    d_max = float(model.displacement(min_gap))
    n = int(max_attempts)
    err = np.full((b, n + 1), np.nan)
    gaps = np.full((b, n), np.nan)
    corr = np.full((b, n), np.nan)
    attempts = np.full(b, -1)
    done = np.abs(e) < eps
    attempts[done] = 0
    err[:, 0] = e
    learns_curve = isinstance(law, CurveLearningLaw)
    mobility = np.ones(b) if not mobility_rel else np.maximum(0.0, 1.0 + mobility_rel * rng.standard_normal(b))
    for i in range(n):
        delta = law.output(st, {})["y"]
        if learns_curve:  # the estimate's bound and inverse (SidePushTask with learning="curve")
            d_des = np.minimum(np.abs(e), law.displacement(st, min_gap))
            gap = law.gap(st, d_des, min_gap)
        else:
            d_des = np.minimum(np.abs(e), d_max)
            gap = np.maximum(model.gap(d_des + delta), min_gap)
        if fixed_gap is not None:
            gap = np.full(b, float(fixed_gap))
        d_act = mobility * plant.displacement(gap)
        if noise_rel:
            d_act = d_act * np.maximum(0.0, 1.0 + noise_rel * rng.standard_normal(b))
        active = ~done
        gaps[:, i] = np.where(active, gap, np.nan)
        corr[:, i] = np.where(active, delta, np.nan)
        e = np.where(active, e - np.sign(e) * d_act, e)
        err[:, i + 1] = np.where(active, e, np.nan)
        if learns_curve:
            st = law.update_where(st, {"gap": gap, "displacement": d_act}, active)
        else:
            st = law.update_where(st, {"e": d_act - d_des}, active)
        hit = active & (np.abs(e) < eps)
        attempts[hit] = i + 1
        done |= hit
    return {"attempts": attempts, "error": err, "gap": gaps, "correction": corr}


def local_ratio(d_act, model="lin", plant=None) -> np.ndarray:
    """Local model ratio ``ρ = F_model′ / F_act′`` at the actual displacement ``d_act``.

    The slope of ``D_s,act`` with respect to the commanded ``D_s,des + Δ`` at that
    operating point: for eq 23 against eq 22, ``ρ = 5.29·0.009042/µm · D_s,act``.
    """
    model = side_model(model) if isinstance(model, str) else model
    plant = ExpSideModel() if plant is None else (side_model(plant) if isinstance(plant, str) else plant)
    d_act = np.asarray(d_act, dtype=float)
    gap = plant.gap(d_act)
    d_cmd = model.displacement(gap)
    return model.slope(d_cmd) / plant.slope(d_act)


def side_nonlinear_gain_range(model="lin", *, plant=None, gains=None, e0=None,
                              max_attempts: int = SIDE_MAX_ATTEMPTS, min_gap: float = MIN_GAP,
                              eps: float = SIDE_EPS) -> dict:
    """Gains for which the nonlinear attempt map converges from every start in the operating range.

    The map (eq 22 plant) is run for every ``(K_s, e0)`` pair in one batch; a gain
    counts as stable when every start reaches ``ε_p`` within ``max_attempts``.

    Returns
    -------
    dict with ``gains``, ``all_converged`` (bool per gain), ``worst_attempts`` (per gain),
    ``range`` (the interval of consecutive converging gains that contains the most
    gains, or None).
    """
    gains = np.round(np.arange(0.0, 6.0001, 0.02), 10) if gains is None else np.asarray(gains, dtype=float)
    e0 = np.linspace(10 * UM, SIDE_GOAL, 59) if e0 is None else np.asarray(e0, dtype=float)
    kk, ee = np.meshgrid(gains, e0, indexing="ij")
    res = side_attempt_map(kk.ravel(), ee.ravel(), model=model, plant=plant, min_gap=min_gap, eps=eps,
                           max_attempts=max_attempts)
    att = res["attempts"].reshape(kk.shape)
    ok = np.all(att >= 0, axis=1)
    worst = np.where(ok, att.max(axis=1), -1)
    return {"gains": gains, "all_converged": ok, "worst_attempts": worst, "range": _longest_run(gains, ok)}


def _longest_run(x: np.ndarray, ok: np.ndarray) -> tuple[float, float] | None:
    best, start = None, None
    for i, flag in enumerate(list(ok) + [False]):
        if flag and start is None:
            start = i
        elif not flag and start is not None:
            if best is None or i - start > best[1] - best[0]:
                best = (start, i)
            start = None
    return None if best is None else (float(x[best[0]]), float(x[best[1] - 1]))


# --- the fluid model's curve as a plant -----------------------------------------------------------
def fluid_side_plant(gaps=None) -> TabulatedSideModel:
    """The fluid model's side-push curve (Fig 6 simulation, ``magctl.plant.fluid``) as ``F_act``.

    Runs the fluid scenario once per call (seconds); gaps default to 370–900 µm.
    """
    from magctl.plant.fluid.scenarios import sidepush_curve

    gaps = np.linspace(MIN_GAP, 900 * UM, 12) if gaps is None else np.asarray(gaps, dtype=float)
    res = sidepush_curve(gaps)
    d = np.abs(res.along)
    keep = np.concatenate([[True], np.diff(d) < 0]) & (d > 0)
    return TabulatedSideModel(tuple(gaps[keep]), tuple(d[keep]), name="fluid")


__all__ = [
    "LinSideModel", "LoopAnalysis", "ReleaseMap", "fluid_side_plant", "front_attempts_identified",
    "front_identified_map", "classify", "front_attempt_map", "front_attempts_markov",
    "front_attempts_monte_carlo", "front_iteration_diagram", "front_loop", "local_ratio",
    "side_attempt_map", "side_full_poles", "side_full_stable_range", "side_iteration_diagram", "side_loop",
    "side_nonlinear_gain_range", "sweep",
]
