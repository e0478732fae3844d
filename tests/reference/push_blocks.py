"""Numpy references of the push tasks (§V) and of the learning laws they step.

The laws: eq 13/18's integrator (:class:`~magctl.control.learning.LearningLaw`), the curve learned online
(:class:`~magctl.control.curve_learning.CurveLearningLaw`, docs/push-control.md §6) and the controller on the
identified release map (:class:`~magctl.control.release_model.ReleasePolicyLaw`, §7). The tasks: front pushing
(eq 10–13) and its two-sphere assembly (Fig 3), side pushing (eq 16–18; with the curve law its push-out turn,
and the front push answering dirt) and its assembly (eq 21), and Fig 15's front-then-side protocol.

Each is written in batched numpy from the equations, as the library's kernels are per trial
(``magctl/control/kernels.py``, ``magctl/control/push/kernels.py``). A task's reference steps its law's reference
(:func:`numpy_form`), the dirt response and the Fig 15 protocol their member tasks' references, so a reference
task runs no kernel at all. The release policy's queries (:func:`nearest`, :func:`success`, :func:`choose`,
:func:`best_delta`) are functions of a library :class:`~magctl.control.release_model.ReleasePolicy`.
"""

from __future__ import annotations

import copy

import numpy as np

from magctl.control.curve_learning import CurveLearningLaw
from magctl.control.kernels import COST_RISE_TOL, HALVINGS
from magctl.control.learning import LearningLaw
from magctl.control.phases import FINISHED, FRONT_PHASE_OFFSET, START, AssemblyStage
from magctl.control.push.assembly import AssemblyTask, FrontThenSideAssemblyTask
from magctl.control.push.front import APPROACH, PUSH, RETRACT, FrontAssemblyTask, FrontPushTask
from magctl.control.push.front import SETTLE as FRONT_SETTLE
from magctl.control.push.side import FRONT_STAGE, PASS, REPOSITION, SETTLE, SIDE_STAGE, SidePushTask
from magctl.control.release_model import ReleasePolicyLaw
from magctl.control.status import Status
from magctl.core.batched import norm, perp, unit
from reference.core_blocks import NumpyForm, SteppedForm

RUNNING, CONVERGED, ATTEMPT_LIMIT = Status.RUNNING, Status.CONVERGED, Status.ATTEMPT_LIMIT
TRACKING_LOST, SPHERE_LOST, STALLED = Status.TRACKING_LOST, Status.SPHERE_LOST, Status.STALLED


def numpy_form(block):
    """``block`` (same parameters) as its reference class of this module: a task's law, a member task."""
    ref = copy.copy(block)
    ref.__class__ = REFERENCES[type(block)]
    return ref


# --- planar geometry ------------------------------------------------------------------------------------
def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """z-component of the 2-D cross product."""
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def rotate(v: np.ndarray, angle) -> np.ndarray:
    """Rotate 2-vectors ``v`` (…, 2) by ``angle`` (scalar or per row) counter-clockwise."""
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], axis=-1)


def arrived(r: np.ndarray, target: np.ndarray, tol: float) -> np.ndarray:
    """Robot within ``tol`` of its target."""
    return norm(r - target) < tol


def around(robot: np.ndarray, obstacle: np.ndarray, target: np.ndarray, clearance, step=np.pi / 4) -> np.ndarray:
    """Next waypoint from ``robot`` to ``target`` that keeps ``clearance`` from ``obstacle``.

    Where the straight segment enters the disc of radius ``clearance`` around the
    obstacle (and the target is outside it), the waypoint is on a slightly larger
    circle, ``step`` radians further round from the robot's bearing, turning the short
    way towards the target's bearing; otherwise the target itself. Stateless and
    batched: called every frame it walks the robot round the disc (a minimal stand-in
    for the paper's wavefront planner, §II).
    """
    d = target - robot
    rel = obstacle - robot
    dd = np.einsum("bi,bi->b", d, d)
    t = np.minimum(np.maximum(np.einsum("bi,bi->b", rel, d) / np.where(dd > 0, dd, 1.0), 0.0), 1.0)   # clip
    closest = norm(robot + t[:, None] * d - obstacle)
    blocked = (closest < clearance) & (norm(target - obstacle) >= clearance)
    a_r = np.arctan2(robot[:, 1] - obstacle[:, 1], robot[:, 0] - obstacle[:, 0])
    a_t = np.arctan2(target[:, 1] - obstacle[:, 1], target[:, 0] - obstacle[:, 0])
    diff = (a_t - a_r + np.pi) % (2 * np.pi) - np.pi
    a = a_r + np.sign(diff) * np.minimum(np.abs(diff), step)
    wp = obstacle + (1.08 * np.asarray(clearance))[..., None] * np.stack([np.cos(a), np.sin(a)], axis=-1)
    return np.where(blocked[:, None], wp, target)


def select_state(mask: np.ndarray, a: dict, b: dict) -> dict:
    """Per trial, ``a``'s entries where ``mask`` holds and ``b``'s elsewhere (nested dicts alike)."""
    out = {}
    for k, va in a.items():
        vb = b[k]
        if isinstance(va, dict):
            out[k] = select_state(mask, va, vb)
        elif isinstance(va, np.ndarray) and va.ndim >= 1 and va.shape[0] == mask.shape[0]:
            out[k] = np.where(mask.reshape((-1,) + (1,) * (va.ndim - 1)), va, vb)
        else:
            out[k] = va
    return out


# --- the learning laws ------------------------------------------------------------------------------------
class RefLearningLaw(NumpyForm, LearningLaw):
    """``y(i) = x(i)``, ``x(i+1) = x(i) + g·e(i)`` (eq 13, eq 18 with the sign in the gain)."""

    def output(self, state, u):
        return {"y": state["x"]}

    def update(self, state, u):
        return {"x": state["x"] + self.gain * u["e"]}

    def update_where(self, state, u, mask) -> dict:
        """The next state with only the trials in ``mask`` advanced (those that just finished an attempt)."""
        return {"x": np.where(mask, state["x"] + self.gain * u["e"], state["x"])}


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


class RefCurveLearningLaw(NumpyForm, CurveLearningLaw):
    """The iterated extended Kalman estimate of ``D_s,act = exp(a − b·x) − c``, its output
    ``y = exp(a) − exp(a₀)``, and the estimate's displacement, inverse and mobility."""

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
        until ``J`` does not rise by more than ``COST_RISE_TOL`` (a pass many times the prior's prediction
        would otherwise throw the exponential's linearisation far past the mode). One iteration is the plain
        EKF step whenever that step lowers ``J``. Covariance in Joseph form at the last linearisation;
        ``b ≥ b_min`` kept.

        Every product is written out per element (:func:`cholesky3`, :func:`quadratic3` for the prior term,
        no LAPACK, no einsum), in the order the kernel (``magctl.control.kernels.curve_update``) takes for one
        trial.
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

    def displacement(self, state, gap) -> np.ndarray:
        """The estimated attempt ``exp(a − b·x) − c`` at ``gap`` (m), per trial."""
        a, b, c = state["theta"][:, 0], state["theta"][:, 1], state["theta"][:, 2]
        return np.exp(a - b * (np.asarray(gap, dtype=float) - self.reference_gap) / self.reference_gap) - c

    def gap(self, state, d_des, min_gap: float) -> np.ndarray:
        """The gap the estimate says gives ``d_des`` (m), not below ``min_gap``; where ``d_des + c`` ≤ 0, the gap
        of a 1 % curve value."""
        a, b, c = state["theta"][:, 0], state["theta"][:, 1], state["theta"][:, 2]
        want = np.asarray(d_des, dtype=float) + c
        floor = 0.01 * np.exp(a)
        g = self.reference_gap * (1.0 + (a - np.log(np.maximum(want, floor))) / b)
        return np.maximum(g, min_gap)

    def mobility(self, state, gap) -> np.ndarray:
        """The estimated attempt at ``gap`` over the prior's there: 1 for a sphere as the prior, ≪ 1 on dirt."""
        return self.displacement(state, gap) / self.prior_displacement(gap)


# --- the release-model controller (docs/push-control.md §7) ------------------------------------------------
TIE_MARGIN = 8
"""Neighbours asked of the tree beyond ``k``, so that the logged attempts tied with the k-th are seen (checked)."""


def _d2(policy, q: np.ndarray, idx: np.ndarray) -> np.ndarray:
    d0 = policy.points[idx, 0] - q[:, None, 0]
    d1 = policy.points[idx, 1] - q[:, None, 1]
    return d0 * d0 + d1 * d1


def nearest(policy, q) -> np.ndarray:
    """``(len(q), k)``: the logged later attempts (indices into ``policy.rows``) nearest each scaled query
    ``q`` (…, 2), nearest first, ties to the earlier one (asked of the policy's k-d tree)."""
    q = np.reshape(np.asarray(q, float), (-1, 2))
    n = policy.rows.size
    kk = min(policy.k + TIE_MARGIN, n)
    _, nb = policy.tree.query(q, k=kk)
    nb = np.reshape(nb, (q.shape[0], kk))
    d2 = _d2(policy, q, nb)
    order = np.lexsort((nb, d2), axis=-1)
    nb, d2 = np.take_along_axis(nb, order, -1), np.take_along_axis(d2, order, -1)
    # every attempt as near as the k-th was among those asked for, unless the last one asked is as near too
    unseen = ~(d2[:, -1] > d2[:, policy.k - 1]) & (kk < n)
    if unseen.any():
        every = np.broadcast_to(np.arange(n), (int(unseen.sum()), n))
        nb[unseen] = np.lexsort((every, _d2(policy, q[unseen], every)), axis=-1)[:, :kk]
    return nb[:, :policy.k]


def _queries(policy, d, previous, delta) -> np.ndarray:
    return np.c_[d + delta, previous] / policy.release_map.scale


def success(policy, d, previous) -> np.ndarray:
    """Estimated success of every candidate δ, shape ``(len(d), len(deltas))``: the share of the ``k`` logged
    later attempts nearest ``(d + δ, R_prev)`` that would have ended within ε_p."""
    d = np.atleast_1d(np.asarray(d, float))
    prev = np.broadcast_to(np.asarray(previous, float), d.shape)
    out = np.empty((d.size, policy.deltas.size))
    for j, delta in enumerate(policy.deltas):
        out[:, j] = policy.hits[j, nearest(policy, _queries(policy, d, prev, delta))].mean(axis=1)
    return out


def choose(policy, d, previous) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``δ*``, its estimated success and the map rows of the ``k`` logged attempts it was read on (nearest
    first) for each ``(d, R_prev)``; the first best candidate where several are as good."""
    d = np.atleast_1d(np.asarray(d, float))
    prev = np.broadcast_to(np.asarray(previous, float), d.shape)
    p = success(policy, d, prev)
    best = p.argmax(axis=1)
    delta = policy.deltas[best]
    return delta, p[np.arange(best.size), best], policy.rows[nearest(policy, _queries(policy, d, prev, delta))]


def best_delta(policy, d, previous) -> tuple[np.ndarray, np.ndarray]:
    """``δ*`` and its estimated success for each ``(d, R_prev)``."""
    p = success(policy, d, previous)
    best = p.argmax(axis=1)
    return policy.deltas[best], p[np.arange(best.size), best]


class RefReleasePolicyLaw(NumpyForm, ReleasePolicyLaw):
    """``y = δ``; ``δ ← δ*(|e|, e + δ)`` (:func:`choose`) after an attempt with a finite error ``e``."""

    def output(self, state, u):
        return {"y": state["x"].copy()}

    def update(self, state, u):
        return self.update_where(state, u, np.ones(np.shape(state["x"]), dtype=bool))

    def update_where(self, state, u, mask) -> dict:
        """``δ ← δ*(|e|, e + δ)`` for the trials in ``mask``; the others keep theirs."""
        e = np.asarray(u["e"], dtype=float)
        m = np.asarray(mask, dtype=bool) & np.isfinite(e)
        x = state["x"].copy()
        nb = state["neighbours"].copy()
        if m.any():
            x[m], _, nb[m] = choose(self.policy, np.abs(e[m]), e[m] + x[m])
        return {"x": x, "neighbours": nb}


# --- the frame every push task shares ---------------------------------------------------------------------
class PushFrame(SteppedForm):
    """A push task's frame in batched numpy (first base of the task references).

    Subclasses define ``_step(st, new, r, spheres, ok)``, which reads the frame's measurements and writes the
    next phase, targets and law state into ``new`` (a copy of the state) for the trials in ``ok`` (running,
    tracked, sphere found), and ``_begin(new, mask, r, spheres)``, which starts an attempt. A trial whose tracker
    reports ``lost`` for more than ``max_lost_frames`` consecutive frames ends with ``TRACKING_LOST``; one whose
    sphere estimate is missing (non-finite) or beyond ``workspace`` from its goal ends with ``SPHERE_LOST``; one
    stuck in a phase for ``phase_timeout_frames`` ends with ``STALLED``. Finished trials hold the robot where it
    was.
    """

    @property
    def law_form(self):
        """The task's learning law as its numpy reference."""
        return numpy_form(self.law)

    def step(self, state, u):
        return self._frame(state, u)

    def _frame(self, state, u):
        r = np.asarray(u["robot_est"], dtype=float)
        spheres = np.asarray(u["spheres_est"], dtype=float)
        lost = np.asarray(u["lost"], dtype=bool)
        new = {k: (v.copy() if isinstance(v, np.ndarray) else v) for k, v in state.items()}
        new["law"] = dict(state["law"])
        running = new["status"] == RUNNING
        new["lost_frames"] = np.where(running & lost, new["lost_frames"] + 1, 0)
        new["frames"] = np.where(running, new["frames"] + 1, new["frames"])
        self._fail(new, running & (new["lost_frames"] > self.max_lost_frames), TRACKING_LOST, r)
        running = new["status"] == RUNNING
        found = self._spheres_found(new, spheres)
        self._fail(new, running & ~lost & ~found, SPHERE_LOST, r)
        running = new["status"] == RUNNING
        self._fail(new, running & (new["frames"] > self.phase_timeout_frames), STALLED, r)
        ok = (new["status"] == RUNNING) & ~lost
        if ok.any():
            self._step(state, new, r, spheres, ok)
        done = new["status"] != RUNNING
        new["phase"] = np.where(done, FINISHED, new["phase"])
        target = np.where(np.isnan(new["target"]), r, new["target"])
        speed = np.where(done, 0.0, new["speed"])
        out = {
            "target": target, "speed_cap": speed, "status": new["status"].copy(),
            "attempt": new["attempt"].copy(), "phase": new["phase"].copy(),
            "correction": self.law_form.output(new["law"], {})["y"].copy(),
        }
        return out, new

    def _fail(self, new, mask, code, r):
        if mask.any():
            new["status"] = np.where(mask, code, new["status"])
            new["target"] = np.where(mask[:, None], r, new["target"])

    def _spheres_found(self, new, spheres) -> np.ndarray:
        idx = list(self.sphere_indices)
        s = spheres[:, idx]
        finite = np.isfinite(s).all(axis=(1, 2))
        far = norm(spheres[:, idx[0]] - new["goal"]) > self.workspace if "goal" in new else False
        return finite & ~far

    def _start(self, new, ok, done, r, spheres):
        """Trials still at ``START``: converged if eq 12 (eq 21) already holds, else the first attempt begins."""
        start = ok & (new["phase"] == START)
        if start.any():
            new["status"] = np.where(start & done, CONVERGED, new["status"])
            self._begin(new, start & ~done, r, spheres)

    def _enter(self, new, mask, phase):
        new["phase"] = np.where(mask, phase, new["phase"])
        new["frames"] = np.where(mask, 0, new["frames"])

    def _finish_attempt(self, new, mask, converged):
        """Count the attempt; converged or limit reached ends the trial. Returns trials that go on."""
        new["attempt"] = np.where(mask, new["attempt"] + 1, new["attempt"])
        conv = mask & converged
        limit = mask & ~converged & (new["attempt"] >= self.max_attempts)
        new["status"] = np.where(conv, CONVERGED, np.where(limit, ATTEMPT_LIMIT, new["status"]))
        return mask & ~conv & ~limit


# --- front pushing (§V-A, eq 10–13) -----------------------------------------------------------------------
class RefFrontPush(PushFrame, FrontPushTask):
    """Approach ``P_ri`` round the sphere → push until eq 11 (or the robot stands where the sphere would be at
    ``P_o = P_g + δu``, eq 10) → retract → settle → eq 12 ends the task, else the law takes
    ``e = (P_g − P_s)·u`` (eq 13, or the release-model law) and the next attempt begins."""

    def _geometry(self, new, r, spheres):
        """Moved sphere ``s``, goal point, pushing direction ``u`` and the eq 12 test."""
        s = spheres[:, self.sphere_indices[0]]
        goal = new["goal"]
        return s, goal, unit(goal - s), norm(goal - s) < self.eps

    def _begin(self, new, mask, r, spheres):
        s, goal, u, _ = self._geometry(new, r, spheres)
        m = mask[:, None]
        delta = self.law_form.output(new["law"], {})["y"]
        p_o = goal + delta[:, None] * u  # eq 10
        new["u"] = np.where(m, u, new["u"])
        new["g_line"] = np.where(m, goal, new["g_line"])
        new["p_ri"] = np.where(m, s - self.approach * u, new["p_ri"])
        new["p_o"] = np.where(m, p_o, new["p_o"])
        new["stand"] = np.where(m, p_o - self.contact * u, new["stand"])
        self._enter(new, mask, APPROACH)

    def _step(self, state, new, r, spheres, ok):
        ph = new["phase"]
        s, _, _, done = self._geometry(new, r, spheres)
        self._start(new, ok, done, r, spheres)
        # approach → push
        app = ok & (ph == APPROACH) & arrived(r, new["p_ri"], self.arrive_tol)
        self._enter(new, app, PUSH)
        # push → retract (eq 11, or the robot stands where the sphere would be at P_o)
        pushing = ok & (ph == PUSH)
        reached = pushing & ((norm(s - new["p_o"]) < self.push_tol) | arrived(r, new["stand"], self.arrive_tol))
        new["back"] = np.where(reached[:, None], r - self.retract * new["u"], new["back"])
        self._enter(new, reached, RETRACT)
        # retract → settle
        ret = ok & (ph == RETRACT) & arrived(r, new["back"], self.arrive_tol)
        self._enter(new, ret, FRONT_SETTLE)
        # settle → measure (eq 12, eq 13) → next attempt
        meas = ok & (ph == FRONT_SETTLE) & (new["frames"] >= self.settle_frames)
        if meas.any():
            e = np.einsum("bi,bi->b", new["g_line"] - s, new["u"])
            go_on = self._finish_attempt(new, meas, done)
            new["law"] = self.law_form.update_where(new["law"], {"e": e}, go_on)
            self._begin(new, go_on, r, spheres)
        self._targets(new, r, s, ok)

    def _targets(self, new, r, s, ok):
        """The servo target and speed cap of the phase, for the trials in ``ok`` (the others keep theirs)."""
        ph = np.where(ok, new["phase"], START)
        tgt = new["target"]
        tgt = np.where((ph == APPROACH)[:, None], around(r, s, new["p_ri"], self.clearance), tgt)
        tgt = np.where((ph == PUSH)[:, None], new["stand"], tgt)
        tgt = np.where(((ph == RETRACT) | (ph == FRONT_SETTLE))[:, None], new["back"], tgt)
        new["target"] = tgt
        new["speed"] = np.where(ok, np.where(ph == PUSH, self.push_speed, self.travel_speed), new["speed"])


class RefFrontAssembly(RefFrontPush, FrontAssemblyTask):
    """The front push with goal ``P_s2 − (R_1 + R_2)·v`` each attempt (``v`` from sphere 1 to sphere 2), ending by
    eq 21."""

    def _geometry(self, new, r, spheres):
        s1, s2 = spheres[:, self.sphere_indices[0]], spheres[:, self.sphere_indices[1]]
        v = unit(s2 - s1)
        goal = s2 - (self.radii[0] + self.radii[1]) * v
        done = norm(s2 - s1) <= self.radii[0] + self.radii[1] + self.eps_as  # eq 21
        return s1, goal, v, done

    def _spheres_found(self, new, spheres):
        s = spheres[:, list(self.sphere_indices)]
        return np.isfinite(s).all(axis=(1, 2)) & (norm(s[:, 0] - s[:, 1]) < self.workspace)


# --- side pushing (§V-B, eq 16–18) ------------------------------------------------------------------------
class RefSidePush(PushFrame, SidePushTask):
    """``D_s,des`` (eq 16, bounded) and ``D_g`` (eq 17) → reposition round the sphere → pass → settle → eq 12 ends
    the task, else the law takes ``e = D_s,act − D_s,des`` (eq 18) or the pass ``(D_g, D_s,act)`` (the curve law,
    with its push-out and its own bound and inverse); with the dirt response, a stuck sphere's front push."""

    def step(self, state, u):
        return self._frame(state, u) if self.front is None else self._frame_with_front(state, u)

    def _frame_with_front(self, state, u):
        """One frame of side passes that hand a stuck sphere to one front push and take it back afterwards.

        The side stage is frozen while the front push runs. It hands over on the frame it measures an attempt
        after which the curve law reads the sphere as stuck (estimated displacement at the contact threshold
        under ``dirt.mobility`` of the prior's) with more than ``dirt.passes`` passes at that bound to go, at
        most ``dirt.fronts`` times; the front push counts as an attempt when it ends, and the side passes
        start afresh from where the sphere lies. A front push ending in a failure (tracking or sphere lost,
        stalled) ends the task with that status.
        """
        side_state = {k: v for k, v in state.items() if k not in ("stage", "fronts", "front")}
        s_out, s_new = self._frame(side_state, u)
        f_out, f_new = numpy_form(self.front).step(state["front"], u)
        in_front = state["stage"] == FRONT_STAGE
        spheres = np.asarray(u["spheres_est"], dtype=float)
        s = spheres[:, self.sphere_indices[0]]
        dist = norm(s_new["goal"] - s)
        measured = ~in_front & (s_new["attempt"] > side_state["attempt"]) & (s_new["status"] == RUNNING)
        stuck = self.law_form.mobility(s_new["law"], self.min_gap) < self.dirt.mobility
        many = dist > self.dirt.passes * self.law_form.displacement(s_new["law"], self.min_gap)
        trigger = measured & stuck & many & (state["fronts"] < self.dirt.fronts)
        if self.dirt_response == "front-first":   # the coarse move first: a front push before any side pass
            trigger |= (~in_front & (state["fronts"] == 0) & (s_new["attempt"] == 0) & (s_new["status"] == RUNNING))
        ended = in_front & (f_out["status"] != RUNNING)
        failed = ended & ~np.isin(f_out["status"], (CONVERGED, ATTEMPT_LIMIT))
        back = ended & ~failed

        side = select_state(in_front, side_state, s_new)
        restart = trigger | back
        side["phase"] = np.where(restart, START, side["phase"])
        side["frames"] = np.where(restart, 0, side["frames"])
        side["target"] = np.where(restart[:, None], np.nan, side["target"])
        if back.any():
            self._finish_attempt(side, back, dist < self.eps)  # the front push was an attempt
        side["status"] = np.where(failed, f_out["status"], side["status"])
        side["phase"] = np.where(side["status"] != RUNNING, FINISHED, side["phase"])

        running = select_state(in_front, f_new, state["front"])
        front = select_state(trigger, self.front.initial_state(len(trigger)), running)
        new = side | {"stage": np.where(trigger, FRONT_STAGE, np.where(ended, SIDE_STAGE, state["stage"])),
                      "fronts": state["fronts"] + trigger, "front": front}

        running_front = in_front & ~ended
        out = dict(s_out)
        for k in ("target", "speed_cap"):
            out[k] = np.where(running_front.reshape((-1,) + (1,) * (np.ndim(f_out[k]) - 1)), f_out[k], s_out[k])
        out["phase"] = np.where(running_front, f_out["phase"] + FRONT_PHASE_OFFSET, s_out["phase"])
        out["gap"] = np.where(in_front, 0.0, s_out["gap"])
        out["status"] = side["status"].copy()
        out["attempt"] = side["attempt"].copy()
        out["phase"] = np.where(side["status"] != RUNNING, FINISHED, out["phase"])
        out["target"] = np.where((ended | trigger)[:, None], np.asarray(u["robot_est"], dtype=float), out["target"])
        out["speed_cap"] = np.where(ended | trigger, 0.0, out["speed_cap"])
        return out, new

    def _frame(self, state, u):
        out, new = super()._frame(state, u)
        out["gap"] = np.where(np.isinf(new["gap"]), 0.0, new["gap"])  # 0: the attempt makes no pass
        return out, new

    def _geometry(self, new, r, spheres):
        """Moved sphere, distance still to go, pushing direction, side of the motion line, eq 12."""
        s = spheres[:, self.sphere_indices[0]]
        to_goal = new["goal"] - s
        u = unit(to_goal)
        side = np.where(cross(u, r - s) >= 0, 1.0, -1.0)
        dist = norm(to_goal)
        return s, dist, u, side, dist < self.eps

    def _begin(self, new, mask, r, spheres):
        s, dist, u, side, _ = self._geometry(new, r, spheres)
        law = self.law_form
        if self.learns_curve:  # the estimate's own bound and inverse (docs/push-control.md §6)
            # the flow pushes the sphere across the pass, away from the robot: aim so the sum points at the goal
            turn = np.arctan(new["push_out"])
            u = np.cos(turn)[:, None] * u + (side * np.sin(turn))[:, None] * perp(u)
            d_des = np.minimum(dist, law.displacement(new["law"], self.min_gap))
        else:
            d_des = np.minimum(dist, self.d_max)  # eq 16, bounded (§V-B step 1)
        if self.fixed_gap is not None:
            gap = np.full(dist.shape, self.fixed_gap)
        elif self.learns_curve:
            gap = law.gap(new["law"], d_des, self.min_gap)
        else:
            delta = law.output(new["law"], {})["y"]
            gap = np.maximum(self.model.gap(d_des + delta), self.min_gap)  # eq 17
        # D_s,des + Δ ≤ 0: eq 22 asks for an infinite gap, i.e. no pass; the attempt only settles and
        # measures D_s,act = 0 (the no-push branch of magctl.stability.switched)
        skip = mask & ~np.isfinite(gap)
        n = side[:, None] * perp(u) * np.where(np.isfinite(gap), gap, 0.0)[:, None]
        m = mask[:, None]
        new["u"] = np.where(m, u, new["u"])
        new["p0"] = np.where(m, s, new["p0"])
        new["start"] = np.where(m, s - self.behind * u + n, new["start"])
        new["end"] = np.where(m, np.where(skip[:, None], r, s + self.ahead * u + n), new["end"])
        new["d_des"] = np.where(mask, d_des, new["d_des"])
        new["gap"] = np.where(mask, gap, new["gap"])
        self._enter(new, mask & ~skip, REPOSITION)
        self._enter(new, skip, SETTLE)

    def _learn_push_out(self, new, mask, s) -> None:
        """Update the push-out ratio from the attempt just measured: the sphere's displacement across the pass
        line, away from the side the robot passed on, over its displacement along it (passes at least
        ``push_out_min`` long); the first measurement is taken whole, later ones with ``push_out_weight``."""
        u, d = new["u"], s - new["p0"]
        robot_side = np.sign(np.einsum("bi,bi->b", new["start"] - new["p0"] + self.behind * u, perp(u)))
        along = np.einsum("bi,bi->b", d, u)
        across = -robot_side * np.einsum("bi,bi->b", d, perp(u))
        use = mask & (along >= self.push_out_min)
        ratio = across / np.where(use, along, 1.0)
        weight = np.where(new["push_out_n"] == 0, 1.0, self.push_out_weight)
        new["push_out"] = np.where(use, new["push_out"] + weight * (ratio - new["push_out"]), new["push_out"])
        new["push_out_n"] = np.where(use, new["push_out_n"] + 1, new["push_out_n"])

    def _step(self, state, new, r, spheres, ok):
        ph = new["phase"]
        s, *_, done = self._geometry(new, r, spheres)
        self._start(new, ok, done, r, spheres)
        rep = ok & (ph == REPOSITION) & arrived(r, new["start"], self.arrive_tol)
        self._enter(new, rep, PASS)
        passed = ok & (ph == PASS) & arrived(r, new["end"], self.arrive_tol)
        self._enter(new, passed, SETTLE)
        meas = ok & (ph == SETTLE) & (new["frames"] >= self.settle_frames)
        if meas.any():
            d_act = np.einsum("bi,bi->b", s - new["p0"], new["u"])
            go_on = self._finish_attempt(new, meas, done)
            if self.learns_curve:
                new["law"] = self.law_form.update_where(new["law"], {"gap": new["gap"], "displacement": d_act},
                                                        go_on)
                self._learn_push_out(new, go_on, s)
            else:  # eq 18 bracket as printed; the law's gain carries the sign
                new["law"] = self.law_form.update_where(new["law"], {"e": d_act - new["d_des"]}, go_on)
            self._begin(new, go_on, r, spheres)
        # the servo target and speed cap of the phase, for the trials in ok (the others keep theirs)
        ph = np.where(ok, new["phase"], START)
        tgt = np.where((ph == REPOSITION)[:, None], around(r, s, new["start"], self.clearance), new["target"])
        tgt = np.where(((ph == PASS) | (ph == SETTLE))[:, None], new["end"], tgt)
        new["target"] = tgt
        new["speed"] = np.where(ok, np.where(ph == PASS, self.pass_speed, self.travel_speed), new["speed"])


class RefAssembly(RefSidePush, AssemblyTask):
    """The side push along the adjusted line at ``θ_n`` to the line sphere 1 → sphere 2 (turned towards the
    robot's side), ``D_s,des`` the gap still to close, ending by eq 21."""

    def _geometry(self, new, r, spheres):
        s1, s2 = spheres[:, self.sphere_indices[0]], spheres[:, self.sphere_indices[1]]
        v = unit(s2 - s1)
        side = np.where(cross(v, r - s1) >= 0, 1.0, -1.0)
        u = rotate(v, side * self.theta_n)
        sep = norm(s2 - s1)
        to_close = np.maximum(sep - self.radii[0] - self.radii[1], 0.0)
        done = sep <= self.radii[0] + self.radii[1] + self.eps_as  # eq 21
        return s1, to_close, u, side, done

    def _spheres_found(self, new, spheres):
        s = spheres[:, list(self.sphere_indices)]
        return np.isfinite(s).all(axis=(1, 2)) & (norm(s[:, 0] - s[:, 1]) < self.workspace)


class RefFrontThenSide(SteppedForm, FrontThenSideAssemblyTask):
    """Fig 15: the front stage every frame; the side stage only in stage 2, which starts the frame after the
    front stage ends at its attempt limit short of eq 21."""

    def step(self, state, u):
        """One frame: the running stage's outputs; stage 2 starts the frame after stage 1 ended short of eq 21."""
        f_out, f_new = numpy_form(self.front).step(state["front"], u)
        s_out, s_new = numpy_form(self.side).step(state["side"], u)
        in_side = state["stage"] == AssemblyStage.SIDE
        handover = ~in_side & (f_out["status"] == ATTEMPT_LIMIT)
        out = {k: np.where(in_side.reshape((-1,) + (1,) * (np.ndim(s_out[k]) - 1)), s_out[k],
                           f_out[k] if k in f_out else np.zeros_like(s_out[k]))
               for k in s_out}
        out["attempt"] = np.where(in_side, f_out["attempt"] + s_out["attempt"], f_out["attempt"])
        out["phase"] = np.where(in_side & (s_out["phase"] != FINISHED), s_out["phase"] + self.SIDE_PHASE_OFFSET,
                                out["phase"])
        out["status"] = np.where(handover, RUNNING, out["status"])
        out["phase"] = np.where(handover, self.SIDE_PHASE_OFFSET, out["phase"])
        out["stage"] = np.where(in_side, AssemblyStage.SIDE, AssemblyStage.FRONT).astype(np.int64)
        new = {"stage": np.where(in_side | handover, AssemblyStage.SIDE, AssemblyStage.FRONT).astype(np.int64),
               "front": f_new, "side": select_state(in_side, s_new, state["side"])}
        return out, new


REFERENCES = {LearningLaw: RefLearningLaw, CurveLearningLaw: RefCurveLearningLaw,
              ReleasePolicyLaw: RefReleasePolicyLaw, FrontPushTask: RefFrontPush, FrontAssemblyTask: RefFrontAssembly,
              SidePushTask: RefSidePush, AssemblyTask: RefAssembly, FrontThenSideAssemblyTask: RefFrontThenSide}
