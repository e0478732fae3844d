"""Side pushing with an online model: the gap → displacement curve re-estimated after every pass and inverted.

The paper's eq 17–18 keep the model ``F`` fixed and integrate the error into a correction ``Δ``; how well
that works depends on how far the plant is from ``F`` (eq 20: ``K_s < 2/ρ``; the switched map's boundary
ρ ≈ 2.25 at ``K_s`` = 0.9). This law learns the curve itself. One attempt moves the sphere

    D_s,act = exp(a − b·x) − c,   x = (D_g − g_ref) / g_ref,

eq 22's form in a well-conditioned parametrisation (``a`` = ln of the pass's displacement at the reference
gap, ``b = k·g_ref``) less ``c``, what the rest of the attempt takes back (repositioning round the sphere
drags it a few µm towards the robot's path). ``θ = (a, b, c)`` is estimated by an iterated extended Kalman
filter over attempts: a random walk of ``a`` (a sphere whose mobility changes, on dirt, is followed),
measurements ``z = D_s,act`` with a relative pass-to-pass scatter and the camera's noise. The prior is eq
22's form fitted to magctl's Fig 6 curve (``models/push.toml`` [side_fit]); the noise levels are ``[online]``.

The next pass inverts the estimate: ``D_s,des`` (eq 16) bounded by the estimated displacement at the
contact threshold, ``D̂_max = exp(a − b·x_min) − c``, and ``D_g = g_ref·(1 + (a − ln(D_s,des + c))/b)``,
not below ``min_gap``.

Why it converges where eq 18 may not (``docs/push-control.md`` §6): eq 18 corrects the model's output
with a fixed gain, so a plant ρ times more mobile than ``F`` multiplies the loop gain by ρ; here the
estimate's displacement error shrinks with every measured pass whatever ρ is, and the step it commands is
the remaining error divided by the estimated mobility — a loop gain ``ρ/ρ̂`` that tends to 1.
"""

from __future__ import annotations

import numpy as np

from magctl.config import load_model
from magctl.control.learning import ATTEMPT, AttemptLaw
from magctl.control.side_models import side_model
from magctl.core.block import Block, StateVar
from magctl.core.checks import check_positive
from magctl.core.errors import MagctlError
from magctl.core.ports import Port


class CurveLearningLaw(AttemptLaw, Block):
    """Extended Kalman estimate of the per-attempt curve ``D_s,act = exp(a − b·x) − c`` over push attempts.

    ``x = (D_g − g_ref)/g_ref``; ``c`` is what the rest of the attempt takes back: repositioning round the
    sphere drags it back towards the robot's path (a few µm at 1 mm clearance, a large share of a small
    final pass), which eq 22's form, fitted to single passes, does not hold.

    Parameters
    ----------
    name : str
        Block name.
    prior : ExpSideModel
        Eq 22's form ``D_s = A·exp(−k·D_g)`` giving the prior mean of ``(a, b)``.
    reference_gap : float
        ``g_ref`` (m), where the prior and the estimate are anchored (500 µm, ``[side_fit] about_gap``).
    prior_log_sigma, prior_rate_sigma : float
        Prior standard deviations of ``a`` (ln units: 0.3 ≈ ±30 % mobility) and of ``b`` relative to its mean.
    prior_offset, prior_offset_sigma : float
        Prior mean and standard deviation of ``c`` (m).
    pass_log_sigma : float
        Relative standard deviation of one pass's displacement about the curve (0.1: 10 % pass to pass).
    measure_sigma : float
        Standard deviation of a measured displacement from the camera (m), added to the pass scatter.
    drift_log_sigma : float
        Random-walk step of ``a`` per attempt (lets the estimate follow a sphere whose mobility changes).
    rate_floor : float
        ``b`` is kept at or above this fraction of the prior's, so the curve stays decreasing and invertible.
    iterations : int
        Gauss–Newton iterations of each measurement update (1: the plain EKF step; ``[online]`` uses 3).

    Ports
    -----
    inputs ``gap`` () — ``D_g`` of the pass just made (m); ``displacement`` () — ``D_s,act`` it gave (m);
    output ``y`` () — the learned curve's displacement at ``g_ref`` minus the prior's (m): how far the
    estimate has moved from the prior, the counterpart of eq 18's ``Δ``.
    """

    def __init__(self, name: str, prior, *, reference_gap: float, prior_log_sigma: float, prior_rate_sigma: float,
                 prior_offset: float, prior_offset_sigma: float, pass_log_sigma: float, measure_sigma: float,
                 drift_log_sigma: float, rate_floor: float, iterations: int = 1, dt: float = ATTEMPT):
        amplitude, rate = getattr(prior, "amplitude", None), getattr(prior, "rate", None)
        if amplitude is None or rate is None:
            raise MagctlError(f"curve learning {name!r}: the prior must be eq 22's form (an 'exp' model), "
                              f"got {getattr(prior, 'name', prior)!r}")
        self.reference_gap = check_positive("reference_gap", reference_gap)
        a0 = np.log(check_positive("prior amplitude", amplitude)) - check_positive("prior rate", rate) * reference_gap
        b0 = rate * reference_gap
        self.prior_mean = np.array([a0, b0, float(prior_offset)])
        self.prior_cov = np.diag([check_positive("prior_log_sigma", prior_log_sigma) ** 2,
                                  (check_positive("prior_rate_sigma", prior_rate_sigma) * b0) ** 2,
                                  check_positive("prior_offset_sigma", prior_offset_sigma) ** 2])
        self.pass_rel_var = check_positive("pass_log_sigma", pass_log_sigma) ** 2
        self.measure_var = check_positive("measure_sigma", measure_sigma) ** 2
        self.drift = np.diag([check_positive("drift_log_sigma", drift_log_sigma, allow_zero=True) ** 2, 0.0, 0.0])
        if not 0.0 < rate_floor <= 1.0:
            raise MagctlError(f"curve learning {name!r}: rate_floor={rate_floor!r} must be in (0, 1]")
        self.b_min = float(rate_floor) * b0
        if int(iterations) != iterations or iterations < 1:
            raise MagctlError(f"curve learning {name!r}: iterations={iterations!r} must be a whole number >= 1")
        self.iterations = int(iterations)
        super().__init__(name, inputs=[Port("gap", (), "m"), Port("displacement", (), "m")],
                         outputs=[Port("y", (), "m")], dt=dt, feedthrough=False)

    # --- the block ---------------------------------------------------------------------------------
    def state_vars(self):
        return (StateVar("theta", (3,), symbol="θ", description="estimate (a, b, c) of D_s = exp(a − b·x) − c"),
                StateVar("cov", (3, 3), symbol="P", description="covariance of the estimate"))

    def initial_state(self, batch, rng=None):
        return {"theta": np.tile(self.prior_mean, (batch, 1)), "cov": np.tile(self.prior_cov, (batch, 1, 1))}

    def kernel(self):
        """The law (:func:`magctl.control.kernels.curve_output`, ``curve_update``): output ``y = exp(a) − exp(a₀)``;
        update one iterated extended Kalman step from ``(gap, displacement)``.

        Predict ``P⁻ = P + Q`` (random walk of ``a``); measure ``z = D_s,act`` against
        ``h(θ) = exp(a − b·x) − c`` with Jacobian ``H = (e, −x·e, −1)``, ``e = exp(a − b·x)``, and variance
        ``R = (σ_pass·e⁻)² + σ_meas²`` at the predicted estimate. The update is Gauss–Newton on the negative
        log posterior ``J(θ) = (θ − θ⁻)ᵀP⁻⁻¹(θ − θ⁻) + (z − h(θ))²/R`` (the iterated EKF), each step halved
        until ``J`` does not rise by more than :data:`~magctl.control.kernels.COST_RISE_TOL` (a pass many times the
        prior's prediction would otherwise throw the exponential's linearisation far past the mode); the prior term
        is a sum of squares through the Cholesky factor of ``P⁻``. One iteration is the plain EKF step whenever that
        step lowers ``J``. Covariance in Joseph form at the last linearisation; ``b ≥ b_min`` kept.
        """
        from magctl.control import kernels as k
        from magctl.core.kernel import Kernel

        return Kernel(output=k.curve_output, update=k.curve_update_step, params=self.kernel_params())

    def kernel_params(self) -> tuple:
        """``(cp, iterations)``: the law's :class:`~magctl.control.kernels.CurveParams` and the Gauss–Newton
        iterations."""
        from magctl.control import kernels as k

        cp = k.CurveParams(reference_gap=float(self.reference_gap), pass_var=float(self.pass_rel_var),
                           measure_var=float(self.measure_var), b_min=float(self.b_min),
                           exp_a0=float(np.exp(self.prior_mean[0])),
                           drift=np.ascontiguousarray(self.drift, dtype=float).ravel())
        return cp, int(self.iterations)

    # --- the inversion -----------------------------------------------------------------------------
    def displacement(self, state, gap) -> np.ndarray:
        """The estimated attempt ``exp(a − b·x) − c`` at ``gap`` (m), per trial (``gap`` broadcast against the
        trials as numpy does; :func:`magctl.control.kernels.curve_displacement`)."""
        from magctl.control import kernels as k

        theta, gap, out = self._broadcast(state, gap)
        k.curve_displacements(theta, self.kernel_params()[0], gap, out.reshape(-1))
        return out

    def gap(self, state, d_des, min_gap: float) -> np.ndarray:
        """The gap the estimate says gives ``d_des`` (m), not below ``min_gap`` (where ``d_des + c`` ≤ 0: no
        positive curve value gives it, and the widest pass is as good as any: ``min_gap`` is not chosen, the
        gap of a 1 % curve value is), per trial (:func:`magctl.control.kernels.curve_gap`)."""
        from magctl.control import kernels as k

        theta, d_des, out = self._broadcast(state, d_des)
        k.curve_gaps(theta, self.kernel_params()[0], d_des, float(min_gap), out.reshape(-1))
        return out

    def mobility(self, state, gap) -> np.ndarray:
        """The estimated attempt at ``gap`` over the prior's there: 1 for a sphere as the prior, ≪ 1 on dirt.

        Taken at the gap the passes are made at (the contact threshold, while the sphere is far): there the
        passes measure the curve directly, whereas its value at ``g_ref`` is an extrapolation along ``b``.
        """
        return self.displacement(state, gap) / self.prior_displacement(gap)

    @staticmethod
    def _broadcast(state, value) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The estimates ``θ`` (n, 3) and ``value`` (n,) of the trials broadcast against ``value``, as the kernels
        take them, and the array their results go to (shaped as the broadcast)."""
        theta = np.asarray(state["theta"], dtype=float)
        value = np.asarray(value, dtype=float)
        shape = np.broadcast_shapes(theta.shape[:1], value.shape)
        rows = np.ascontiguousarray(np.broadcast_to(theta, (*shape, 3)).reshape(-1, 3))
        return rows, np.ascontiguousarray(np.broadcast_to(value, shape).reshape(-1)), np.empty(shape)

    def prior_displacement(self, gap):
        """The prior's attempt ``exp(a₀ − b₀·x) − c₀`` at ``gap`` (m)."""
        a0, b0, c0 = self.prior_mean
        x = (np.asarray(gap, dtype=float) - self.reference_gap) / self.reference_gap
        return np.exp(a0 - b0 * x) - c0


def curve_learning_law(prior=None, name: str = "side_law", **overrides) -> CurveLearningLaw:
    """The law with the prior and noise levels of ``models/push.toml`` (``[side_fit]``, ``[online]``).

    ``prior`` defaults to ``exp-fit`` (eq 22's form fitted to magctl's Fig 6 curve); ``overrides`` replace
    any ``[online]`` value by keyword (SI).
    """
    params = load_model("push")
    online = params.online
    kw = {"reference_gap": float(params.side_fit.about_gap),
          **{key: float(online[key]) for key in online}}
    unknown = set(overrides) - set(kw)
    if unknown:
        raise MagctlError(f"curve learning: unknown parameters {sorted(unknown)}; known: {sorted(kw)}")
    kw |= {k: float(v) for k, v in overrides.items()}
    return CurveLearningLaw(name, side_model("exp-fit") if prior is None else prior, **kw)
