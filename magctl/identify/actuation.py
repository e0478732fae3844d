"""The stick-slip drive's speed curve from open-loop segments (paper §IV-C: stick-slip at ~0.4 mm/s).

The robot model's steady speed under a constant field (:func:`magctl.plant.robot.steady_speed`,
docs/plant-actuator.md) is

    ``v = f · η ℓ [cos θ₀ − cos θ_a]₊``,  ``θ_a = atan(b_osc/|B_xy|) / √(1 + (2πf τ_θ)²)``,
    ``τ_θ = c_θ ζ/(m|B_xy|)``,

with slip efficiency ``η`` (``robot.toml [robot] slip_efficiency_1``), break-away angle ``θ₀``
(``break_angle_deg``: the amplitude threshold of the curve) and pitch drag ratio ``c_θ`` (``pitch_drag_ratio_1``:
where the curve peaks in frequency). :func:`speed_curve` fits them to the steady speeds of open-loop segments,
each measured by :func:`steady_segment_speed`. Settings are ``models/identify.toml`` ``[actuation]``.
"""

from __future__ import annotations

from dataclasses import replace
from typing import NamedTuple

import numpy as np
from scipy.optimize import least_squares

from magctl.config import Params, load_model
from magctl.identify.estimate import Estimate, IdentifyError, NotIdentified
from magctl.plant._stickslip import StickSlipParams, load_robot
from magctl.plant.robot import steady_speed

FILE, TABLE = "robot.toml", "robot"
KEYS = ("slip_efficiency_1", "break_angle_deg", "pitch_drag_ratio_1")
"""The fitted parameters as written in ``models/robot.toml``, in the order of the fit's vector
``x = (η, θ₀ [deg], c_θ)``."""


def settings() -> Params:
    """``models/identify.toml`` ``[actuation]`` (SI after loading)."""
    return load_model("identify").actuation


def _name(key: str) -> str:
    return f"{FILE}:{TABLE}.{key}"


class SegmentSpeed(NamedTuple):
    """A segment's steady speed [m/s], its standard uncertainty [m/s] and the frames it was measured over."""

    speed: float
    uncertainty: float
    frames: int


def steady_segment_speed(t, robot_est, skip_frames: int | None = None, *,
                         config: Params | None = None) -> SegmentSpeed:
    """Steady speed of one open-loop segment (constant command): the slope of a least-squares line through the
    tracker's positions after the transient.

    Each axis is fitted as ``p(t) = p₀ + v t`` over frames ``skip … n−1``; the speed is ``|v|`` and its standard
    uncertainty ``√(v_x² σ_vx² + v_y² σ_vy²)/|v|`` from the fit's residual scatter. The first ``skip_frames`` are
    the transient (default ``steady_skip_frames``, 10): the camera latency (2 frames, ``camera.toml``), the heading
    and tilt settling (``τ_ψ ≈ 0.26`` frames, ``τ_θ`` shorter, at 2 mT) and the Kalman tracker's velocity
    settling (~5 frames after a speed step). The tracker correlates neighbouring residuals, so the uncertainty is
    on the low side; :func:`speed_curve` weights segments by frame count and scales by the fit's own residual
    instead.

    Parameters
    ----------
    t : (n,) array, s
    robot_est : (n, 2) array, m
        Estimates over the segment (rows with NaN are left out).
    skip_frames : int, optional
    config : Params, optional
        ``models/identify.toml`` ``[actuation]``.
    """
    if skip_frames is None:
        skip_frames = (settings() if config is None else config).steady_skip
    skip = int(skip_frames)
    t = np.asarray(t, dtype=float).ravel()[skip:]
    p = np.asarray(robot_est, dtype=float).reshape(-1, 2)[skip:]
    if len(t) != len(p):
        raise IdentifyError("steady_segment_speed: t and robot_est must have one row per frame")
    ok = np.isfinite(t) & np.all(np.isfinite(p), axis=1)
    t, p = t[ok], p[ok]
    n = len(t)
    if n < 3:
        raise IdentifyError(f"steady_segment_speed: {n} frames after skipping {skip} (need ≥ 3)")
    tc = t - t.mean()
    sxx = float(np.sum(tc * tc))
    if sxx <= 0:
        raise IdentifyError("steady_segment_speed: the frame times do not advance")
    v = (tc @ (p - p.mean(axis=0))) / sxx
    resid = p - p.mean(axis=0) - np.outer(tc, v)
    var_v = np.sum(resid**2, axis=0) / (n - 2) / sxx
    spd = float(np.hypot(*v))
    unc = float(np.sqrt(np.sum(v**2 * var_v)) / spd) if spd > 0 else float(np.sqrt(var_v.mean()))
    return SegmentSpeed(spd, unc, n)


class CurveFit(NamedTuple):
    """What :func:`speed_curve` identified and what it could not: ``not_identified`` maps
    ``file:table.key`` (:attr:`Estimate.name`) to the reason."""

    estimates: list[Estimate]
    not_identified: dict[str, str]


def _with(params: StickSlipParams, x) -> StickSlipParams:
    return replace(params, slip_efficiency=float(x[0]), break_angle=float(np.deg2rad(x[1])),
                   pitch_drag_ratio=float(x[2]))


def speed_curve(b_xy, b_osc, freq, speed, n_frames, evidence: str, params: StickSlipParams | None = None, *,
                config: Params | None = None) -> CurveFit:
    """Slip efficiency ``η`` and, where the segments determine them, break angle ``θ₀`` and pitch drag ratio
    ``c_θ`` of the stick-slip model (§IV-C; see the module docstring for ``v(f, b_osc, |B_xy|)``).

    Weighted least squares (``scipy.optimize.least_squares``, trust region within bounds) of the model's steady
    speed on the segments' measured speeds, in relative terms and weighted by frame count: residuals
    ``r_i = √(n_i/n̄) (v(x; field_i) − v_i) / max(v_i, φ v_max)`` with the floor ``φ = speed_floor_ratio`` (the
    stick-slip step scatter is proportional to speed; with absolute residuals the fast segments' larger scatter
    would make the covariance below too small). Every other robot parameter (geometry, moment, film) is
    ``params``'; only ``x`` is fitted. Covariance ``C = s² (JᵀJ)⁻¹`` from the Jacobian at the optimum, scaled by
    the residual variance ``s² = Σ r_i² / (N − p)``; uncertainties are ``√C_jj`` in the key's unit.

    The three are fitted together first. ``θ₀`` and ``c_θ`` are kept only when the segments span the amplitude
    threshold and the frequency peak well enough to tell them apart: ``N > 3``, ``θ₀`` to within
    ``max_break_angle_uncertainty_deg`` (absolute: a break angle near 0 is determined in degrees, not in
    percent), ``c_θ`` to within ``max_relative_uncertainty_ratio`` and the relative-sensitivity Jacobian
    (columns ``∂r/∂ln x_j``) of condition number at most ``max_condition``. Otherwise only ``η`` is fitted, with
    ``θ₀`` and ``c_θ`` held at ``params``' values (so that the folder's three values reproduce the segments as
    well as they can; its uncertainty does not include theirs), and the other two go to ``not_identified``
    with the reason. ``v`` is proportional to ``η``, so ``η`` needs only two segments that move.

    Parameters
    ----------
    b_xy : (N, 2) or (N,) array, T
        In-plane static field of each segment (vector or magnitude).
    b_osc : (N,) array, T
        Oscillating (out-of-plane) amplitude.
    freq : (N,) array, Hz
    speed : (N,) array, m/s
        Measured steady speed (:func:`steady_segment_speed`).
    n_frames : (N,) array
        Frames each speed was measured over (the weights).
    evidence : str
    params : StickSlipParams, optional
        The robot model to start from and to hold the unfitted parameters at (default ``load_robot()``).
    config : Params, optional
        ``models/identify.toml`` ``[actuation]``.

    Returns
    -------
    CurveFit
        ``(estimates, not_identified)``.

    Raises
    ------
    NotIdentified
        Fewer than two segments in which the model's robot moves (nothing determines ``η``).
    """
    p0 = load_robot() if params is None else params
    cfg = settings() if config is None else config
    bxy = np.asarray(b_xy, dtype=float)
    bxy = np.hypot(bxy[..., 0], bxy[..., 1]) if bxy.ndim == 2 else bxy.ravel()
    bo, f = np.asarray(b_osc, dtype=float).ravel(), np.asarray(freq, dtype=float).ravel()
    v, w = np.asarray(speed, dtype=float).ravel(), np.asarray(n_frames, dtype=float).ravel()
    N = len(v)
    if not (len(bxy) == len(bo) == len(f) == len(w) == N):
        raise IdentifyError("speed_curve: one field, frequency, speed and frame count per segment")
    ok = np.isfinite(bxy) & np.isfinite(bo) & np.isfinite(f) & np.isfinite(v) & (w > 0)
    bxy, bo, f, v, w = bxy[ok], bo[ok], f[ok], v[ok], w[ok]
    N = len(v)
    moving = int(np.count_nonzero(steady_speed(p0, bxy, bo, f) > 0))
    if moving < 2:
        raise NotIdentified(f"slip_efficiency_1: {moving} of {N} segments drive the model's robot above its "
                            "stick-slip threshold; η needs at least two that move")
    v_ref = np.maximum(v, float(cfg.speed_floor) * max(float(v.max()), 1e-300))
    sw = np.sqrt(w / w.mean())
    x0 = np.array([p0.slip_efficiency, np.rad2deg(p0.break_angle), p0.pitch_drag_ratio])
    ratio = bo / np.maximum(bxy, 1e-12)
    where = (f"{N} open-loop segments ({int(w.sum())} frames), {np.unique(f).size} frequencies "
             f"{f.min():g}–{f.max():g} Hz, {np.unique(np.round(ratio, 6)).size} amplitude "
             f"ratios b_osc/|B_xy| {ratio.min():.3g}–{ratio.max():.3g}")

    def full(x, free):
        out = x0.copy()
        out[free] = x
        return out

    def residuals(x, free):
        return sw * (steady_speed(_with(p0, full(x, free)), bxy, bo, f) - v) / v_ref

    def fit(free):
        lo = np.array([1e-6, 0.0, 1e-4])[free]
        hi = np.array([np.inf, 60.0, 100.0])[free]
        start = np.clip(x0[free], lo + 1e-9, hi)
        if 1 in free:  # θ₀ = 0 sits on its bound: start just inside
            start[list(free).index(1)] = max(start[list(free).index(1)], 0.5)
        res = least_squares(residuals, start, args=(free,), bounds=(lo, hi), x_scale=np.maximum(np.abs(start), 1e-3),
                            method="trf", xtol=1e-12, ftol=1e-12, gtol=1e-12)
        dof = N - len(free)
        s2 = 2.0 * res.cost / dof if dof > 0 else np.nan
        J = res.jac
        try:
            cov = np.linalg.inv(J.T @ J) * s2
        except np.linalg.LinAlgError:
            cov = np.full((len(free), len(free)), np.inf)
        sd = np.sqrt(np.abs(np.diag(cov)))
        cond = float(np.linalg.cond(J * res.x)) if np.all(np.isfinite(J)) else np.inf
        return res, sd, cond, s2

    def rms(x, free):
        return float(np.sqrt(np.mean(residuals(x, free) ** 2)))

    not_identified: dict[str, str] = {}
    full_ok = False
    rel_max, cond_max = float(cfg.max_relative_uncertainty), float(cfg.max_condition)
    angle_max = float(np.rad2deg(cfg.max_break_angle_uncertainty))
    if N > 3:
        free = [0, 1, 2]
        res, sd, cond, s2 = fit(free)
        rel = sd / np.maximum(np.abs(res.x), 1e-12)
        full_ok = bool(res.success and np.all(np.isfinite(sd)) and sd[1] <= angle_max and rel[2] <= rel_max
                       and cond <= cond_max)
        if not full_ok:
            why = (f"the segments ({where}) do not span the amplitude threshold and the frequency peak well enough "
                   f"to determine it apart from the others: fitted with η, θ₀, c_θ free (weighted rms residual "
                   f"{100 * rms(res.x, free):.2g} %), θ₀ = {res.x[1]:.3g} ± {sd[1]:.2g}° (limit ± {angle_max:g}°), "
                   f"c_θ = {res.x[2]:.3g} ± {100 * rel[2]:.2g} % (limit {100 * rel_max:g} %), Jacobian condition "
                   f"{cond:.3g} (limit {cond_max:g})")
    else:
        why = f"{N} segments cannot determine 3 parameters (need more than 3, spanning threshold and peak)"
    if not full_ok:
        free = [0]
        res, sd, cond, s2 = fit(free)
        not_identified = {_name("break_angle_deg"): f"break_angle_deg: {why}",
                          _name("pitch_drag_ratio_1"): f"pitch_drag_ratio_1: {why}"}
        held = (f"; θ₀ = {x0[1]:.4g}°, c_θ = {x0[2]:.4g} held at the model's values (the uncertainty does not "
                "include theirs)")
    else:
        held = ""
    if not np.isfinite(s2):
        raise NotIdentified(f"slip_efficiency_1: {N} segments leave no residual degree of freedom to scale the "
                            "uncertainty by")
    keys = KEYS if full_ok else KEYS[:1]
    text = (f"{evidence}: least-squares fit of the stick-slip speed curve (§IV-C) to {where}; frame-count weights, "
            f"weighted rms residual {100 * rms(res.x, free):.2g} % of the speeds, Jacobian condition "
            f"{cond:.3g}{held}")
    estimates = [Estimate(FILE, TABLE, k, float(res.x[i]), float(sd[i]), text) for i, k in enumerate(keys)]
    return CurveFit(estimates, not_identified)

