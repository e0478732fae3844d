"""The camera's parameters from run logs: position noise, frame lag, dropped frames (paper §II: 30 frames/s camera).

Each fit returns an :class:`~magctl.identify.estimate.Estimate` for ``models/camera.toml`` ``[camera]``, or raises
:class:`~magctl.identify.estimate.NotIdentified` saying what the logs lack. Settings are ``models/identify.toml``
``[camera]``.

* :func:`noise_from_stationary` — ``position_noise_px`` (σ, pixels) from windows in which the robot stands still.
  What the log holds is the tracker's estimate, quantised to the pixel grid by the camera and smoothed by the
  Kalman filter (:mod:`magctl.sensing.camera`, :mod:`magctl.sensing.tracker`), so its variance is neither σ² nor
  linear in it; the fit inverts magctl's own Camera + Tracker blocks by simulation (indirect inference):
  ``S_sim(σ) = S_obs``, solved by Brent's method.
* :func:`latency_from_commands` — ``latency_frames`` (L) from the logged commands and estimates: the model's robot
  is driven open loop by the commands and seen through a camera of lag ``L`` and the tracker, for every
  ``L ≤ L_max``; the lag whose predicted velocity of the estimate best matches the logged one (least squares with a
  free speed scale and a free heading time factor) wins.
* :func:`drop_rate` — ``drop_probability_ratio`` from gaps in the rig's frame counter, with the Agresti–Coull
  (Wilson-centred) binomial uncertainty.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np
from scipy.optimize import brentq

from magctl.config import Params, load_model
from magctl.core.diagram import Diagram
from magctl.core.simulation import simulate
from magctl.identify.estimate import Estimate, IdentifyError, NotIdentified
from magctl.plant._stickslip import StickSlipParams, load_robot
from magctl.plant.robot import StickSlipRobot
from magctl.sensing.camera import Camera, camera_params
from magctl.sensing.tracker import Tracker

FILE, TABLE = "camera.toml", "camera"
_SENSOR_WIRES = [("camera.robot_meas", "tracker.robot_meas"), ("camera.heading_meas", "tracker.heading_meas"),
                 ("camera.spheres_meas", "tracker.spheres_meas"), ("camera.valid", "tracker.valid")]
_WIDE_VIEW_PX = 100_000
"""Sensor width and height [px] of the simulated camera of the lag fit: the predicted path never leaves its view."""


def settings() -> Params:
    """``models/identify.toml`` ``[camera]`` (SI after loading)."""
    return load_model("identify").camera


# --- position noise ---------------------------------------------------------------------------------------
def _sensor(sigma_px: float, params: Params, tracker_px: float | None = None) -> tuple[Camera, Tracker]:
    """The rig's camera (positions mode, no lag, no drops) with noise σ and its Kalman tracker, whose
    ``R = (σ_R s)² + s²/12`` uses ``σ_R = tracker_px``, or σ itself when None (as on the simulated rig, where
    both read the same ``camera.toml``)."""
    cam = Camera(n_spheres=0, latency_frames=0, position_noise_px=sigma_px, heading_noise=0.0,
                 drop_probability=0.0, params=params)
    trk_px = sigma_px if tracker_px is None else tracker_px
    return cam, Tracker(n_spheres=0, position_noise_px=trk_px, params=params)


def _pooled_variance(est: Sequence[np.ndarray], settle: int) -> tuple[float, int]:
    """Pooled within-window variance of the estimates after the first ``settle`` frames, and its degrees of
    freedom: ``Σ_i Σ_axes Σ_k (x_ik − x̄_i)² / Σ_i 2 (n_i − settle − 1)``."""
    ss, dof = 0.0, 0
    for w in est:
        x = w[settle:]
        ss += float(np.sum((x - x.mean(axis=0)) ** 2))
        dof += 2 * (len(x) - 1)
    return ss / dof, dof


class _StationarySim:
    """Camera + Tracker on a still robot, one trial per window and replicate (trial ``r·W + i`` is replicate ``r``
    of window ``i``, ``n_i`` frames long), each at its own sub-pixel offset drawn uniformly in the pixel. The seed,
    the trial indices and the offsets are fixed, so every σ sees the same draws (common random numbers)."""

    def __init__(self, lengths: list[int], settle: int, replicates: int, seed: int, params: Params,
                 tracker_px: float | None = None):
        self.params, self.settle, self.lengths, self.seed = params, settle, lengths, seed
        self.tracker_px = tracker_px
        self.W, self.R = len(lengths), replicates
        centre = np.array([params.camera.width // 2, params.camera.height // 2], dtype=float)  # px
        offsets = np.random.default_rng([seed, 1]).random((self.R * self.W, 2))
        self.T = max(lengths)
        pos = float(params.camera.pixel_size) * (centre + offsets)
        self.position = np.broadcast_to(pos[:, None, :], (len(pos), self.T, 2))
        self.cache: dict[float, np.ndarray] = {}

    def statistic(self, sigma_px: float) -> np.ndarray:
        """Pooled variance [px²] of the simulated estimate, one value per replicate, shape ``(R,)``."""
        sigma_px = float(max(sigma_px, 0.0))
        if sigma_px in self.cache:
            return self.cache[sigma_px]
        cam, tr = _sensor(sigma_px, self.params, self.tracker_px)
        d = Diagram("stationary", [cam, tr], _SENSOR_WIRES,
                    inputs={"position": "camera.position", "heading": "camera.heading",
                            "spheres": "camera.spheres"}, outputs={"robot_est": "tracker.robot_est"})
        B = self.W * self.R
        res = simulate(d, self.T, batch=B, seed=self.seed, record=[],
                       inputs={"position": self.position, "heading": 0.0, "spheres": np.zeros((0, 2))})
        est = res.outputs["robot_est"] / float(self.params.camera.pixel_size)
        out = np.array([_pooled_variance([est[r * self.W + i, :n] for i, n in enumerate(self.lengths)],
                                         self.settle)[0] for r in range(self.R)])
        self.cache[sigma_px] = out
        return out


def noise_from_stationary(windows: Sequence[np.ndarray], evidence: str, params: Params | None = None, *,
                          config: Params | None = None, tracker_noise_px: float | None = None) -> Estimate:
    """``position_noise_px``: the camera's centroid noise σ [px] from frames where the robot stands still.

    The statistic is the pooled within-window variance of the logged estimate after the tracker's settling
    frames, ``S = Σ_i Σ_k |p̂_ik − p̄_i|² / Σ_i 2(n_i − n_s − 1)`` [px²]. The camera rounds ``p + σ s n`` to the
    pixel grid (§VI-B: 1 px = 7.5 µm) and the Kalman tracker smooths it with ``R = (σ s)² + s²/12``, so ``S``
    is a non-linear function of σ that also depends on where inside its pixel each window sits. It is computed
    by running the Camera and Tracker blocks (positions mode, no lag, no drops: neither changes a still robot's
    variance) on a still robot for each window's length, ``R`` replicates with common random numbers across σ.

    Each simulated window sits at its own sub-pixel offset drawn uniformly in the pixel (only the offset
    matters; the whole-pixel position is the view's centre). The offset is a nuisance parameter the data barely
    determine: a window's mean is pulled towards its pixel's centre when σ ≲ 0.3 px, so placing the simulated
    robot at the observed mean makes flips between pixels rarer than they were (σ̂ 0.23 for a true 0.10 px in
    a 5-window trial), and solving for the offset whose quantised mean matches makes any σ → 0 fit a window
    that flips (a Bernoulli two-level series). Drawing the offsets keeps ``E[S_sim(σ)] = E[S_obs]`` exact over
    offsets and puts their effect in the replicates' spread, so the uncertainty grows where quantisation hides σ
    (±0.04–0.06 px at 0.1–0.3 px, ±0.014 px at 0.6 px, for 1 000 frames in 5 windows) instead of a bias.

    σ̂ solves ``mean_r S_sim,r(σ) = S_obs`` (Brent's method; ``S_sim`` rises with σ); its standard uncertainty
    is the replicates' spread of ``S`` (the sampling spread of the observed statistic for data of this shape)
    over the slope ``dS_sim/dσ``, times ``√(1 + 1/R)`` for the simulation's own error.

    Parameters
    ----------
    windows : sequence of (n_i, 2) arrays
        ``robot_est`` [m] over frames in which the robot stands still (coils off), one array per window.
    evidence : str
        Where the windows come from (logs, frames), for the estimate's source.
    params : Params, optional
        Parsed ``models/camera.toml`` of the rig (pixel size, tracker noise); default the shipped one.
    config : Params, optional
        ``models/identify.toml`` ``[camera]`` (settings ``noise_*``).
    tracker_noise_px : float, optional
        The σ the rig's tracker was configured with (its ``R``), when it is not the camera's true σ (a tracker
        that read the old ``camera.toml``); default: ``R`` follows the candidate σ, as on the simulated rig.

    Raises
    ------
    NotIdentified
        The observed variance is no larger than quantisation alone leaves (σ below what the pixel grid hides).
    IdentifyError
        No window is longer than the settling frames, or the variance exceeds ``noise_max_px``'s.
    """
    params = camera_params() if params is None else params
    cfg = settings() if config is None else config
    settle, R = int(cfg.noise_settle), int(cfg.noise_replicates)
    pixel = float(params.camera.pixel_size)
    arrs = []
    for i, w in enumerate(windows):
        a = np.asarray(w, dtype=float)
        if a.ndim != 2 or a.shape[1] != 2:
            raise IdentifyError(f"stationary window {i}: expected an (n, 2) array of positions, got {a.shape}")
        a = a[np.all(np.isfinite(a), axis=1)]
        if len(a) > settle + 2:
            arrs.append(a)
    if not arrs:
        raise IdentifyError(f"no stationary window has more than {settle + 2} finite frames "
                            f"(noise_settle_frames = {settle})")
    est_px = [a / pixel for a in arrs]
    s_obs, dof = _pooled_variance(est_px, settle)
    n_frames = sum(len(a) - settle for a in arrs)
    sim = _StationarySim([len(a) for a in arrs], settle, R, int(cfg.noise_seed), params, tracker_noise_px)
    where = f"{n_frames} stationary frames in {len(arrs)} windows"

    s0 = float(sim.statistic(0.0).mean())
    if s_obs <= s0 + 1e-12:
        raise NotIdentified(
            f"position_noise_px: the estimate does not move over {where} (pooled variance {s_obs:.3g} px² ≤ "
            f"{s0:.3g} px² with σ = 0): the noise is below what the {pixel * 1e6:.3g} µm pixel grid hides")
    hi = float(cfg.noise_max)

    def gap(sig: float) -> float:
        return float(sim.statistic(sig).mean()) - s_obs

    if gap(hi) < 0:
        raise IdentifyError(f"position_noise_px: pooled variance {s_obs:.3g} px² over {where} exceeds what "
                            f"σ = {hi:g} px gives ({gap(hi) + s_obs:.3g} px²); is the robot really still?")
    sigma = brentq(gap, 0.0, hi, xtol=1e-4, rtol=1e-6)
    h = max(0.1 * sigma, 0.02)
    lo_s, hi_s = max(sigma - h, 0.0), sigma + h
    slope = (gap(hi_s) - gap(lo_s)) / (hi_s - lo_s)
    spread = float(np.std(sim.statistic(sigma), ddof=1))
    unc = spread / slope * np.sqrt(1.0 + 1.0 / R) if slope > 0 else float("inf")
    return Estimate(FILE, TABLE, "position_noise_px", float(sigma), float(unc),
                    f"{evidence}: pooled variance of the tracker's estimate {s_obs:.4g} px² over {where} "
                    f"({dof} dof, first {settle} frames of each dropped), matched by simulating magctl's Camera + "
                    f"Kalman Tracker ({R} replicates, common random numbers; slope {slope:.3g} px²/px)")


# --- frame lag --------------------------------------------------------------------------------------------
def _wide_view(params: Params) -> Params:
    """``params`` with a ``_WIDE_VIEW_PX``-pixel square sensor: a path predicted open loop never leaves it."""
    cam = params.camera
    values = {k: cam[k] for k in cam} | {"width": _WIDE_VIEW_PX, "height": _WIDE_VIEW_PX}
    table = Params(cam._path, values, cam.sources, cam.units, cam.raw)
    return Params(params._path, {k: params[k] for k in params} | {"camera": table}, params.sources, params.units,
                  params.raw)


def _onsets(b_static: np.ndarray, b_osc: np.ndarray, freq: np.ndarray) -> np.ndarray:
    """Frames ``k ≥ 1`` whose command differs from frame ``k − 1``'s."""
    cmd = np.column_stack([b_static, b_osc, freq])
    scale = np.maximum(np.abs(cmd).max(axis=0), 1e-300)
    changed = np.any(np.abs(np.diff(cmd, axis=0)) > 1e-9 * scale, axis=1)
    return np.flatnonzero(changed) + 1


def turn_scaled(robot: StickSlipParams, factor: float) -> StickSlipParams:
    """The robot with its heading time constant ``τ_ψ = ζ/(m|B|)`` times ``factor`` and nothing else changed:
    the film gap ``h_f`` divided by it (``ζ ∝ 1/h_f``) and the pitch drag ratio too (``τ_θ = c_θ ζ/(m|B|)`` and
    so the speed curve stay as they were)."""
    return replace(robot, film_gap=robot.film_gap / factor, pitch_drag_ratio=robot.pitch_drag_ratio / factor)


def predicted_path(b_static, b_osc, freq, start, heading0: float, dt: float, robot: StickSlipParams) -> np.ndarray:
    """Position [m], ``(T, 2)``, of the model's robot (step variability off) driven open loop by the commands
    from ``start``/``heading0``; event ``k``'s command moves it during frame ``k → k+1``, row ``k`` is frame
    ``k``'s pose."""
    rob = StickSlipRobot("robot", robot, position=np.asarray(start, dtype=float), heading=float(heading0),
                         variability=False, dt=dt)
    res = simulate(Diagram("open_loop", [rob], [],
                           inputs={"b_static": "robot.b_static_delivered", "b_osc": "robot.b_osc_delivered",
                                   "freq": "robot.freq_delivered"}, outputs={"position": "robot.position"}, dt=dt),
                   len(b_osc), batch=1, seed=0, record=[], inputs={"b_static": b_static, "b_osc": b_osc, "freq": freq})
    return res.outputs["position"][0]


def predicted_estimates(path: np.ndarray, latencies: Sequence[int], dt: float, params: Params) -> np.ndarray:
    """The tracker's estimate [m], ``(len(latencies), T, 2)``, of ``path`` seen by a noise-free camera of each lag
    (primed with the first pose, as the simulated rig's camera is) and the Kalman tracker (``R`` at the file's σ,
    as on the rig).

    A camera of lag ``L`` delivers at frame ``k`` the frame sampled at ``k − L`` (before it, the primed first
    pose); with no noise and no drops that is the camera block at lag 0 fed the delayed path, so all lags run in
    one batch. The path is moved by whole pixels to the middle of a sensor too large to leave (quantisation only
    sees the sub-pixel position) and moved back.
    """
    pixel = float(params.camera.pixel_size)
    path = np.asarray(path, dtype=float)
    shift = pixel * np.round((0.5 * _WIDE_VIEW_PX * pixel - path[0]) / pixel)
    delayed = np.stack([np.concatenate([np.repeat(path[:1], L, axis=0), path[:len(path) - L]]) for L in latencies])
    cam = Camera(n_spheres=0, latency_frames=0, position_noise_px=0.0, heading_noise=0.0, drop_probability=0.0,
                 params=_wide_view(params), dt=dt)
    tr = Tracker(n_spheres=0, params=params, dt=dt)  # R at the rig's σ: only the camera is noise-free
    d = Diagram("seen", [cam, tr], _SENSOR_WIRES, inputs={"position": "camera.position", "heading": "camera.heading",
                                                         "spheres": "camera.spheres"},
                outputs={"robot_est": "tracker.robot_est"}, dt=dt)
    res = simulate(d, path.shape[0], batch=len(latencies), seed=0, record=[],
                   inputs={"position": delayed + shift, "heading": 0.0, "spheres": np.zeros((0, 2))})
    return res.outputs["robot_est"] - shift


def _velocity(est: np.ndarray, w: int, dt: float) -> np.ndarray:
    """Mean velocity over ``w`` frames, ``(p[k + w] − p[k]) / (w T)``, ``(…, T − w, 2)``."""
    return (est[..., w:, :] - est[..., :-w, :]) / (w * dt)


def _scaled_rss(v_obs: np.ndarray, v_pred: np.ndarray) -> tuple[float, float]:
    """``min_a Σ |v − a v_L|²`` and its ``a``."""
    a = float(np.sum(v_obs * v_pred) / max(np.sum(v_pred * v_pred), 1e-300))
    return float(np.sum((v_obs - a * v_pred) ** 2)), a


def latency_from_commands(t, b_static, b_osc, freq, robot_est, heading_est, evidence: str,
                          params: StickSlipParams | None = None, *, camera: Params | None = None,
                          config: Params | None = None) -> Estimate:
    """``latency_frames``: the camera's processing lag L [frames] from how the estimate answers the commands.

    The model's robot (:class:`~magctl.plant.robot.StickSlipRobot`, step variability off) is driven open loop by
    the logged commands from the first observed pose (:func:`predicted_path`) and seen by a noise-free camera of
    lag ``L`` and the Kalman tracker (:func:`predicted_estimates`), ``L = 0 … L_max``. Velocities over ``w``
    frames, ``v[k] = (p̂[k+w] − p̂[k])/(wT)``, on the log and on each prediction alike, are compared by least
    squares with a free speed scale ``a = Σ v·v_L / Σ v_L·v_L``, so a mis-modelled speed curve scales the
    prediction without shifting it in time: ``RSS_L = min_a Σ |v − a v_L|²``. Only velocities are compared: the
    open-loop position drifts from the logged one, its velocity follows the commanded heading.

    A turn's delay is the lag plus the heading's settling (``τ_ψ = ζ/(m|B|)``, ≈ 0.26 frames at 2 mT with the
    shipped robot), so a mis-modelled turning drag would pass for lag. ``τ_ψ`` is therefore a second free
    (nuisance) factor ``κ`` (:func:`turn_scaled`, a grid ``latency_turn_factors`` refined by a parabola in
    ``ln κ``) and ``RSS_L = min_κ RSS_{L,κ}`` (profiled); starts, stops and speed changes carry the lag alone and
    separate the two. ``L̂ = argmin RSS_L``.

    Uncertainty (the lag is an integer): 0 when ``L̂`` beats both neighbours decisively, else 1. The margin is a
    Gaussian likelihood ratio ``ln Λ_j = (n_eff/2) ln(RSS_j / RSS_L̂)`` for ``j = L̂ ± 1``, with
    ``n_eff = n (1 − ρ)/(1 + ρ)`` (``ρ`` the lag-1 autocorrelation of the best fit's residuals, which the
    ``w``-frame differences and the tracker correlate); decisive means ``Λ_j ≥ latency_likelihood_ratio`` for
    both neighbours and ``L̂ < L_max``.

    Parameters
    ----------
    t : (T,) array, s
        Frame times (uniform at the frame rate, §II: 30 frames/s).
    b_static : (T, 2) array, T;  b_osc : (T,) array, T;  freq : (T,) array, Hz
        Command of each event, applied by the rig from its frame on (coil dynamics, τ = L/R ≈ 2 ms, neglected).
    robot_est : (T, 2) array, m;  heading_est : (T,) array, rad
        Tracker estimates of each event (NaN where lost; the first finite one is the start pose).
    evidence : str
    params : StickSlipParams, optional
        The robot model (default :func:`~magctl.plant._stickslip.load_robot`).
    camera : Params, optional
        ``models/camera.toml`` (pixel size, tracker noise); default the shipped one.
    config : Params, optional
        ``models/identify.toml`` ``[camera]`` (settings ``latency_*``).

    Raises
    ------
    NotIdentified
        The commands never change: a constant command has no onset to time the lag by.
    """
    robot = load_robot() if params is None else params
    cam = camera_params() if camera is None else camera
    cfg = settings() if config is None else config
    t = np.asarray(t, dtype=float)
    b_static = np.asarray(b_static, dtype=float).reshape(-1, 2)
    b_osc, freq = np.asarray(b_osc, dtype=float).ravel(), np.asarray(freq, dtype=float).ravel()
    est = np.asarray(robot_est, dtype=float).reshape(-1, 2)
    heading = np.asarray(heading_est, dtype=float).ravel()
    T = len(t)
    if not (len(b_static) == len(b_osc) == len(freq) == len(est) == len(heading) == T):
        raise IdentifyError("latency_from_commands: t, commands and estimates must have one row per frame")
    L_max, w = int(cfg.latency_max), int(cfg.latency_smooth)
    if T < L_max + 3 * w + 2:
        raise IdentifyError(f"latency_from_commands: {T} frames are too few (need > {L_max + 3 * w + 2})")
    dt = float(np.median(np.diff(t)))
    if not dt > 0 or np.any(np.abs(np.diff(t) - dt) > 0.25 * dt):
        raise IdentifyError("latency_from_commands: frame times must be uniform (one event per frame)")
    seen = np.flatnonzero(np.all(np.isfinite(est), axis=1) & np.isfinite(heading))
    if len(seen) == 0:
        raise IdentifyError("latency_from_commands: the robot is never tracked")
    k0 = int(seen[0])
    cmd = (b_static[k0:], b_osc[k0:], freq[k0:])
    onsets = _onsets(*cmd)
    if len(onsets) == 0:
        raise NotIdentified("latency_frames: the commands never change, so there is no onset to time the "
                            "camera's lag by")
    v_obs = _velocity(est[k0:], w, dt)
    ok = np.all(np.isfinite(v_obs), axis=1)
    vo = v_obs[ok]
    lags = list(range(L_max + 1))
    factors = np.atleast_1d(np.asarray(cfg.latency_turn_factors, dtype=float))
    rss = np.empty((len(factors), len(lags)))
    for i, kappa in enumerate(factors):
        path = predicted_path(*cmd, est[k0], heading[k0], dt, turn_scaled(robot, float(kappa)))
        v_pred = _velocity(predicted_estimates(path, lags, dt, cam), w, dt)
        rss[i] = [_scaled_rss(vo, v_pred[j][ok])[0] for j in lags]
    profile, kappa_hat = _profile(rss, np.log(factors))
    best = int(np.argmin(profile))
    path = predicted_path(*cmd, est[k0], heading[k0], dt, turn_scaled(robot, float(np.exp(kappa_hat[best]))))
    v_best = _velocity(predicted_estimates(path, [best], dt, cam)[0], w, dt)[ok]
    rss_best, scale = _scaled_rss(vo, v_best)
    resid = vo - scale * v_best
    n = resid.size
    rho = float(np.mean([_lag1(resid[:, i]) for i in range(2)]))
    n_eff = float(np.clip(n * (1 - rho) / (1 + rho), 1.0, n))
    neighbours = [j for j in (best - 1, best + 1) if 0 <= j <= L_max]
    lam = {j: 0.5 * n_eff * np.log(profile[j] / max(profile[best], 1e-300)) for j in neighbours}
    threshold = float(np.log(float(cfg.latency_likelihood)))
    decisive = best < L_max and all(v >= threshold for v in lam.values())
    margin = ", ".join(f"ln Λ vs L={j}: {v:.3g}" for j, v in lam.items())
    table = ", ".join(f"{r / profile[best]:.3g}" for r in profile)
    edge = f"; L = L_max = {L_max} is the edge of the search" if best == L_max else ""
    return Estimate(FILE, TABLE, "latency_frames", float(best), 0.0 if decisive else 1.0,
                    f"{evidence}: {len(onsets)} command onsets over {T - k0} frames; velocity of the estimate over "
                    f"{w} frames vs the model's robot + camera(L) + Kalman tracker, free speed scale {scale:.3g} "
                    f"and heading time factor {np.exp(kappa_hat[best]):.3g}; RSS_L/RSS_min for L = 0…{L_max}: "
                    f"[{table}]; n_eff = {n_eff:.0f}, {margin} (decisive ≥ {threshold:.3g}){edge}")


def _profile(rss: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per column of ``rss`` (rows: grid ``x``, increasing), the minimum over ``x`` and where it is: the grid's
    best point refined by the parabola through it and its neighbours (kept when it lies between them)."""
    best, where = rss.min(axis=0), x[np.argmin(rss, axis=0)]
    for j in range(rss.shape[1]):
        i = int(np.argmin(rss[:, j]))
        if 0 < i < len(x) - 1:
            c = np.polyfit(x[i - 1:i + 2], rss[i - 1:i + 2, j], 2)
            if c[0] > 0:
                xm = -c[1] / (2 * c[0])
                if x[i - 1] < xm < x[i + 1]:
                    best[j], where[j] = min(best[j], float(np.polyval(c, xm))), xm
    return best, where


def _lag1(x: np.ndarray) -> float:
    x = x - x.mean()
    den = float(np.sum(x * x))
    return float(np.clip(np.sum(x[1:] * x[:-1]) / den, -0.99, 0.99)) if den > 0 else 0.0


# --- dropped frames ---------------------------------------------------------------------------------------
def drop_rate(frame_numbers_per_run: Sequence[Sequence[int]], evidence: str) -> Estimate:
    """``drop_probability_ratio``: the fraction of frames the camera never delivered.

    Per run the rig's own frame counter should count up by one per frame; frames expected are
    ``last − first + 1`` (drops before the first or after the last delivered frame cannot be seen), frames
    missing are the expected ones not delivered. With ``x`` missing of ``n`` expected over all runs the estimate
    is ``p̂ = x/n`` and its standard uncertainty is the Agresti–Coull form at ``z = 1`` (the Wilson interval's
    centre), ``√(p̃(1 − p̃)/ñ)`` with ``ñ = n + 1``, ``p̃ = (x + ½)/ñ``: non-zero when no frame was dropped
    (≈ 0.71/n, the Wilson upper 1σ bound being 1/(n + 1)).

    Raises
    ------
    IdentifyError
        A run's frame numbers are not increasing (a counter reset or a mixed log).
    NotIdentified
        No run has a frame.
    """
    x = n = 0
    runs = 0
    for i, frames in enumerate(frame_numbers_per_run):
        f = np.asarray(frames)
        if f.size == 0:
            continue
        if not np.issubdtype(f.dtype, np.integer):
            if not np.all(np.isfinite(f)) or np.any(f != np.round(f)):
                raise IdentifyError(f"run {i}: frame numbers must be whole numbers")
            f = f.astype(np.int64)
        if np.any(np.diff(f) <= 0):
            k = int(np.flatnonzero(np.diff(f) <= 0)[0])
            raise IdentifyError(f"run {i}: frame numbers do not increase at index {k + 1} ({f[k]} → {f[k + 1]})")
        expected = int(f[-1] - f[0] + 1)
        x += expected - f.size
        n += expected
        runs += 1
    if n == 0:
        raise NotIdentified("drop_probability_ratio: no frames in the logs")
    nt = n + 1.0
    pt = (x + 0.5) / nt
    unc = float(np.sqrt(pt * (1 - pt) / nt))
    return Estimate(FILE, TABLE, "drop_probability_ratio", x / n, unc,
                    f"{evidence}: {x} of {n} frames missing from the frame counter of {runs} runs "
                    f"(Agresti–Coull 1σ)")
