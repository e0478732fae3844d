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
from magctl.control.learning import ATTEMPT
from magctl.core.block import Block, StateVar
from magctl.core.checks import check_positive
from magctl.core.errors import MagctlError
from magctl.core.ports import Port

COST_RISE_TOL = 1e-9
"""A Gauss–Newton step of the update counts as not raising ``J`` when it raises it by less than this fraction of
``1 + J``: far above the rounding of ``J`` (~1e-16; near the mode successive steps change ``J`` by that much
either way, and numpy's and libm's ``exp`` differ in the last bit), far below any rise the halving guards against.
Without it a step is halved or not by rounding noise, and the two engines' estimates part by ~1e-6."""


HALVINGS = 30
"""Most halvings of one Gauss–Newton step (after them the step is taken as it is)."""


def cholesky3(p00, p10, p11, p20, p21, p22):
    """The lower Cholesky factor ``L`` of a symmetric positive-definite 3×3 matrix from its lower triangle
    (element-wise: scalars or arrays of them), as ``(l00, l10, l11, l20, l21, l22)``."""
    l00 = np.sqrt(p00)
    l10 = p10 / l00
    l20 = p20 / l00
    l11 = np.sqrt(p11 - l10 * l10)
    l21 = (p21 - l20 * l10) / l11
    l22 = np.sqrt(p22 - l20 * l20 - l21 * l21)
    return l00, l10, l11, l20, l21, l22


def quadratic3(chol, d0, d1, d2):
    """``dᵀ P⁻¹ d = |L⁻¹ d|²`` with ``chol`` = :func:`cholesky3` of ``P`` (forward substitution, a sum of squares:
    no cancellation, whatever the conditioning of ``P``)."""
    l00, l10, l11, l20, l21, l22 = chol
    y0 = d0 / l00
    y1 = (d1 - l10 * y0) / l11
    y2 = (d2 - l20 * y0 - l21 * y1) / l22
    return y0 * y0 + y1 * y1 + y2 * y2


class CurveLearningLaw(Block):
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

    def output(self, state, u):
        return {"y": np.exp(state["theta"][:, 0]) - np.exp(self.prior_mean[0])}

    def update(self, state, u):
        return self.update_where(state, u, np.ones(np.shape(state["theta"])[0], dtype=bool))

    def update_where(self, state, u, mask) -> dict:
        """One iterated extended Kalman step from ``(gap, displacement)`` for the trials in ``mask``; the others
        keep theirs.

        Predict ``P⁻ = P + Q`` (random walk of ``a``); measure ``z = D_s,act`` against
        ``h(θ) = exp(a − b·x) − c`` with Jacobian ``H = (e, −x·e, −1)``, ``e = exp(a − b·x)``, and variance
        ``R = (σ_pass·e⁻)² + σ_meas²`` at the predicted estimate. The update is Gauss–Newton on the negative
        log posterior ``J(θ) = (θ − θ⁻)ᵀP⁻⁻¹(θ − θ⁻) + (z − h(θ))²/R`` (the iterated EKF), each step halved
        until ``J`` does not rise by more than :data:`COST_RISE_TOL` (a pass many times the prior's prediction
        would otherwise throw the exponential's linearisation far past the mode). One iteration is the plain
        EKF step whenever that step lowers ``J``. Covariance in Joseph form at the last linearisation;
        ``b ≥ b_min`` kept.

        Every product is written out per element (:func:`cholesky3`, :func:`quadratic3` for the prior term,
        no LAPACK, no einsum), in the order the compiled kernel
        (:func:`magctl.control.kernels.curve_update`) repeats for one trial.
        """
        theta, cov = state["theta"], state["cov"]
        x = (np.asarray(u["gap"], dtype=float) - self.reference_gap) / self.reference_gap
        z = np.asarray(u["displacement"], dtype=float)
        p = cov + self.drift
        chol = cholesky3(p[:, 0, 0], p[:, 1, 0], p[:, 1, 1], p[:, 2, 0], p[:, 2, 1], p[:, 2, 2])
        th = theta[:, 0], theta[:, 1], theta[:, 2]
        e0 = np.exp(th[0] - th[1] * x)
        r = self.pass_rel_var * e0 * e0 + self.measure_var

        def cost(t):
            miss = z - (np.exp(t[0] - t[1] * x) - t[2])
            return quadratic3(chol, t[0] - th[0], t[1] - th[1], t[2] - th[2]) + miss * miss / r

        it, j_it = th, cost(th)
        for _ in range(self.iterations):
            e = np.exp(it[0] - it[1] * x)
            h = e, -x * e, -np.ones_like(e)
            ph = tuple(p[:, i, 0] * h[0] + p[:, i, 1] * h[1] + p[:, i, 2] * h[2] for i in range(3))
            s = h[0] * ph[0] + h[1] * ph[1] + h[2] * ph[2] + r
            gain = tuple(ph[i] / s for i in range(3))
            innovation = z - (e - it[2]) - (h[0] * (th[0] - it[0]) + h[1] * (th[1] - it[1])
                                           + h[2] * (th[2] - it[2]))
            step = tuple(th[i] + gain[i] * innovation - it[i] for i in range(3))
            trial = tuple(it[i] + step[i] for i in range(3))
            j_trial = cost(trial)
            for _halving in range(HALVINGS):
                worse = ~(j_trial <= j_it + COST_RISE_TOL * (1.0 + j_it))
                if not worse.any():
                    break
                step = tuple(np.where(worse, 0.5 * step[i], step[i]) for i in range(3))
                trial = tuple(np.where(worse, it[i] + step[i], trial[i]) for i in range(3))
                j_trial = np.where(worse, cost(trial), j_trial)
            it, j_it = trial, np.minimum(j_trial, j_it)
        new_theta = np.stack([it[0], np.maximum(it[1], self.b_min), it[2]], axis=-1)
        # Joseph form: A = (I − K·H)·P⁻, then A·(I − K·H)ᵀ + R·K·Kᵀ
        ikh = [[(1.0 if i == j else 0.0) - gain[i] * h[j] for j in range(3)] for i in range(3)]
        a = [[ikh[i][0] * p[:, 0, j] + ikh[i][1] * p[:, 1, j] + ikh[i][2] * p[:, 2, j] for j in range(3)]
             for i in range(3)]
        rows = [np.stack([a[i][0] * ikh[j][0] + a[i][1] * ikh[j][1] + a[i][2] * ikh[j][2] + r * gain[i] * gain[j]
                          for j in range(3)], axis=-1) for i in range(3)]
        new_cov = np.stack(rows, axis=-2)
        keep = ~np.asarray(mask, dtype=bool)
        return {"theta": np.where(keep[:, None], theta, new_theta), "cov": np.where(keep[:, None, None], cov, new_cov)}

    def kernel(self):
        """The compiled law (:func:`magctl.control.kernels.curve_output`, ``curve_update``): the same iterated
        EKF step per trial."""
        from magctl.control import kernels as k
        from magctl.core.kernel import Kernel

        return Kernel(output=k.curve_output, update=k.curve_update_step, params=self.kernel_params())

    def kernel_params(self) -> tuple:
        """``(cp, iterations)``: the law's floats as :mod:`magctl.control.kernels` indexes them (``C_*``) and
        the Gauss–Newton iterations."""
        from magctl.control import kernels as k

        cp = np.zeros(k.N_CP)
        cp[[k.C_GREF, k.C_PASS_VAR, k.C_MEAS_VAR, k.C_B_MIN]] = (self.reference_gap, self.pass_rel_var,
                                                                 self.measure_var, self.b_min)
        cp[k.C_EXP_A0] = np.exp(self.prior_mean[0])  # as output() computes it
        cp[k.C_DRIFT:k.C_DRIFT + 9] = self.drift.ravel()
        return cp, self.iterations

    # --- the inversion -----------------------------------------------------------------------------
    def displacement(self, state, gap) -> np.ndarray:
        """The estimated attempt ``exp(a − b·x) − c`` at ``gap`` (m), per trial."""
        a, b, c = state["theta"][:, 0], state["theta"][:, 1], state["theta"][:, 2]
        return np.exp(a - b * (np.asarray(gap, dtype=float) - self.reference_gap) / self.reference_gap) - c

    def gap(self, state, d_des, min_gap: float) -> np.ndarray:
        """The gap the estimate says gives ``d_des`` (m), not below ``min_gap`` (where ``d_des + c`` ≤ 0: no
        positive curve value gives it, and the widest pass is as good as any: ``min_gap`` is not chosen, the
        gap of a 1 % curve value is)."""
        a, b, c = state["theta"][:, 0], state["theta"][:, 1], state["theta"][:, 2]
        want = np.asarray(d_des, dtype=float) + c
        floor = 0.01 * np.exp(a)
        g = self.reference_gap * (1.0 + (a - np.log(np.maximum(want, floor))) / b)
        return np.maximum(g, min_gap)

    def mobility(self, state, gap) -> np.ndarray:
        """The estimated attempt at ``gap`` over the prior's there: 1 for a sphere as the prior, ≪ 1 on dirt.

        Taken at the gap the passes are made at (the contact threshold, while the sphere is far): there the
        passes measure the curve directly, whereas its value at ``g_ref`` is an extrapolation along ``b``.
        """
        return self.displacement(state, gap) / self.prior_displacement(gap)

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
    from magctl.control.push.common import side_model

    params = load_model("push")
    online = params.online
    kw = {"reference_gap": float(params.side_fit.about_gap),
          **{key: float(online[key]) for key in online}}
    unknown = set(overrides) - set(kw)
    if unknown:
        raise MagctlError(f"curve learning: unknown parameters {sorted(unknown)}; known: {sorted(kw)}")
    kw |= {k: float(v) for k, v in overrides.items()}
    return CurveLearningLaw(name, side_model("exp-fit") if prior is None else prior, **kw)
