"""Assembly as optimisation: the next pass for N spheres, planned on the pass map with casadi and IPOPT.

Each attempt the planner chooses one straight pass ``a → b`` of the robot. It predicts where every
sphere will be after it, ``P' = P + ΔP(P; a, b)`` (the pass map of :mod:`magctl.control.pass_model`,
scaled by the mobility learned so far), and minimises the arrangement's squared bond errors there
(:class:`~magctl.control.arrangement.Arrangement`)::

    min_{a, b}  Σ_k (|P'_j − P'_i| − L_k)² / σ²  +  w·|b − a|
    s.t.        dist(P_i, segment ab) ≥ min_gap + margin     every sphere (no contact, Fig 6)
                |a − P_i|, |b − P_i| ≥ end clearance           the repositioning keep-out reaches both ends
                L_min ≤ |b − a| ≤ L_max,  a, b inside the camera field (less a margin)

(σ = 10 µm). The problem is smooth but not convex: the side a line passes each sphere on is a discrete
choice. The planner samples passes first — every sphere, :data:`directions` directions, both sides, the
gaps of ``[plan] sample_gaps`` — and evaluates them in one call, the objective and the constraints mapped over
the samples (casadi ``Function.map``; the objective only where the bounds are kept). It refines the
``starts`` best with IPOPT (casadi ``nlpsol``) and returns the best refined pass, or the best sample when
IPOPT improves on none;
samples of equal cost (a pair's mirror images) rank in sample order (:data:`TIE`). After the pass it
measures the spheres again and plans the next one (receding horizon).

The problem is stated once, in casadi. The sample map and the derivatives IPOPT evaluates each iteration
run as casadi's generated C, built once per problem into a cache (:func:`cache_dir`) when a C compiler is
found; without one casadi's virtual machine runs them, with the same plans.

The mobility ``m`` (one number per trial) is the least-squares ratio of the displacements measured to the
ones predicted over the passes so far (``[online]`` style: prior 1, each pass weighted by its predicted
displacement), so a slow or dirty slide shortens the gaps instead of stalling.

:class:`GreedyPlanner` is the baseline: the paper's method extended one sphere at a time — sphere ``k``
side-pushed towards where the arrangement puts it (:meth:`Arrangement.placement`) along eq 21's adjusted
line at ``θ_n`` = 30° from its line to the goal, turned to the robot's side, the gap from eq 17 with
eq 22's form fitted to our plant (``exp-fit``).
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import numpy as np

from magctl.config import load_model
from magctl.control.arrangement import Arrangement
from magctl.control.learning import ATTEMPT
from magctl.control.pass_model import PassMap
from magctl.control.push_params import with_defaults
from magctl.control.side_models import side_model
from magctl.core.block import Block, StateVar
from magctl.core.errors import MagctlError
from magctl.core.ports import Port
from magctl.core.units import MM
from magctl.sensing.camera import field_of_view

SIGMA = 10e-6
"""Scale of the bond errors in the objective (m): the objective is in units of (10 µm)²."""
FEASIBLE_TOL = 1e-9
"""A sampled pass keeps the bounds when it breaks none by more than this (m)."""
TIE = 1e-9
"""Sample costs within this (relative, at least absolute) of each other are equal: they differ by rounding
(the mirrored passes of a pair), and the earlier sample comes first."""
SAME_COST = 1e-6
"""A refined pass replaces the best so far only when it is lower by more than this (relative, at least
absolute): IPOPT's ``tol`` of 1e-6 leaves the same optimum reached from two starts this far apart."""
@dataclass(frozen=True)
class PlanLimits:
    """The bounds every planned pass keeps (metres), from ``models/push.toml`` ``[plan]`` and the camera's field of
    view (:func:`~magctl.sensing.camera.field_of_view`, shrunk by ``[common] field_margin_um``)."""

    min_gap: float
    end_clearance: float
    min_length: float
    max_length: float
    field: tuple[float, float, float, float]
    length_weight: float

    @classmethod
    def default(cls) -> PlanLimits:
        push = load_model("push")
        p = push.plan
        m = float(push.common.field_margin)
        w, h = field_of_view()
        return cls(float(push.side.min_gap) + float(p.gap_margin), float(p.end_clearance), float(p.min_length),
                   float(p.max_length), (m, m, w - m, h - m), float(p.length_weight))

    def violations(self, spheres, a, b) -> np.ndarray:
        """Largest violation of the bounds (m, 0 where kept) by each pass ``a[k] → b[k]`` (``(K, 2)`` each)."""
        spheres = np.asarray(spheres, float)
        a, b = np.atleast_2d(np.asarray(a, float)), np.atleast_2d(np.asarray(b, float))
        d = b - a
        length = np.hypot(d[:, 0], d[:, 1])
        rel = spheres[None] - a[:, None]                                   # (K, N, 2)
        t = np.clip(np.einsum("kni,ki->kn", rel, d) / np.maximum(length ** 2, 1e-30)[:, None], 0.0, 1.0)
        gap = np.linalg.norm(rel - t[..., None] * d[:, None], axis=-1).min(axis=1)
        ends = np.minimum(np.linalg.norm(rel, axis=-1), np.linalg.norm(spheres[None] - b[:, None], axis=-1)).min(1)
        x0, y0, x1, y1 = self.field
        out = [self.min_gap - gap, self.end_clearance - ends, self.min_length - length, length - self.max_length]
        for p in (a, b):
            out += [x0 - p[:, 0], p[:, 0] - x1, y0 - p[:, 1], p[:, 1] - y1]
        return np.maximum(0.0, np.max(out, axis=0))

    def violation(self, spheres, a, b) -> float:
        """Largest violation of the bounds by the pass ``a → b`` (m, 0 when it keeps them all)."""
        return float(self.violations(spheres, a, b)[0])


@dataclass(frozen=True)
class Pass:
    """One planned pass: the robot goes from ``start`` to ``end`` (m); the prediction it was chosen on."""

    start: np.ndarray
    end: np.ndarray
    predicted: np.ndarray
    cost: float
    error: float
    solver: str
    seconds: float


CACHE_ENV = "MAGCTL_CACHE"
C_FLAGS = ("-O2", "-shared", "-fPIC")
"""How casadi's generated C is built (``-O3 -march=native`` measured no faster on the B-spline evaluations)."""
_DERIVATIVES = {"nlp_grad_f": "grad_f", "nlp_jac_g": "jac_g", "nlp_hess_l": "hess_lag"}
"""The derivative functions of the problem IPOPT evaluates each iteration (the costly ones), by the names casadi
generates them under and the ``nlpsol`` options that take them."""


def cache_dir() -> Path:
    """Where the planner's compiled problems live: ``casadi`` under ``$MAGCTL_CACHE`` or ``~/.cache/magctl``."""
    root = os.environ.get(CACHE_ENV)
    return (Path(root) if root else Path.home() / ".cache" / "magctl") / "casadi"


def c_compiler() -> str | None:
    """The C compiler for casadi's generated code: ``$CC``, else ``cc``, ``gcc`` or ``clang``; None without one."""
    for name in (os.environ.get("CC"), "cc", "gcc", "clang"):
        path = shutil.which(name) if name else None
        if path:
            return path
    return None


def compile_functions(name: str, functions: list[ca.Function]) -> dict[str, ca.Function] | None:
    """``functions`` through casadi's generated C: built once into :func:`cache_dir` under a hash of the source
    (and casadi's version, and the flags), loaded as casadi externals of the same names. None when there is no C
    compiler or the build fails (the caller keeps casadi's virtual machine)."""
    cc = c_compiler()
    if cc is None:
        return None
    gen = ca.CodeGenerator(f"{name}.c")
    for f in functions:
        gen.add(f)
    source = gen.dump()
    digest = hashlib.sha256("\n".join([ca.__version__, *C_FLAGS, source]).encode()).hexdigest()[:20]
    folder = cache_dir()
    lib = folder / f"{name}_{digest}.so"
    if not lib.exists():
        stem = folder / f"{name}_{digest}.{os.getpid()}"
        src, tmp = stem.with_name(stem.name + ".c"), stem.with_name(stem.name + ".so")
        try:
            folder.mkdir(parents=True, exist_ok=True)
            src.write_text(source)
            subprocess.run([cc, *C_FLAGS, str(src), "-o", str(tmp), "-lm"], check=True, capture_output=True)
            os.replace(tmp, lib)           # atomic: another process building the same problem keeps a whole file
        except (OSError, subprocess.CalledProcessError) as exc:
            err = exc.stderr.decode(errors="replace").strip()[-300:] if getattr(exc, "stderr", None) else str(exc)
            warnings.warn(f"assembly planner: casadi's generated code did not build ({err}); "
                          "casadi's virtual machine evaluates the problem instead", RuntimeWarning, stacklevel=4)
            return None
        finally:
            src.unlink(missing_ok=True)
            tmp.unlink(missing_ok=True)
    try:
        return {f.name(): ca.external(f.name(), str(lib)) for f in functions}
    except RuntimeError as exc:
        warnings.warn(f"assembly planner: {lib} did not load ({str(exc).strip()[-200:]}); "
                      "casadi's virtual machine evaluates the problem instead", RuntimeWarning, stacklevel=4)
        return None


class AssemblyPlanner:
    """The next pass for an arrangement of N spheres, optimised on the pass map (see the module docstring).

    Parameters
    ----------
    target : Arrangement
        What to assemble.
    pass_map : PassMap, optional
        The displacement model (``models/pass_map.toml``).
    limits : PlanLimits, optional
        The bounds every pass keeps.
    starts, directions, max_iter : int, optional
        IPOPT starts, sampled directions, IPOPT iterations per start (``[plan]``).
    compiled : bool, optional
        Evaluate the problem through casadi's generated C (built once per problem into :func:`cache_dir`) or
        through casadi's virtual machine (False): the same plans. By default the generated C when a C compiler is
        found; True insists on it.

    Attributes
    ----------
    compiled : bool
        Whether the generated C is in use.
    profile : dict
        The last :meth:`plan`: samples and feasible samples, IPOPT solves and iterations, and the seconds spent
        sampling, refining and predicting.
    """

    def __init__(self, target: Arrangement, pass_map: PassMap | None = None, limits: PlanLimits | None = None, *,
                 starts: int | None = None, directions: int | None = None, max_iter: int | None = None,
                 compiled: bool | None = None):
        p = load_model("push").plan
        self.target = target
        self.map = pass_map if pass_map is not None else PassMap.load()
        self.limits = limits if limits is not None else PlanLimits.default()
        self.starts = int(p.starts if starts is None else starts)
        self.directions = int(p.directions if directions is None else directions)
        self.max_iter = int(p.max_iter if max_iter is None else max_iter)
        self.sample_gaps = np.atleast_1d(np.asarray(p.sample_gaps, float))
        if self.starts < 0 or self.directions < 1 or self.max_iter < 1:
            raise MagctlError("assembly planner: starts >= 0, directions >= 1 and max_iter >= 1 needed")
        self.behind = float(load_model("push").side.behind)
        self.profile: dict = {}
        self._build(compiled)

    # --- the problem in casadi -------------------------------------------------------------------
    def _build(self, compiled: bool | None) -> None:
        n, lim = self.target.n, self.limits
        x = ca.MX.sym("x", 4)                       # a, b in mm
        prm = ca.MX.sym("p", 2 * n + 1)             # sphere centres (mm, row-major) and the mobility
        spheres = ca.reshape(prm[: 2 * n], 2, n).T
        a, b = x[:2], x[2:]
        moved = spheres + prm[2 * n] * self.map.symbolic(spheres, a, b)
        bonds = self.target.bonds
        err = [ca.norm_2(moved[int(j), :] - moved[int(i), :]) - t / MM
               for (i, j, _), t in zip(bonds, self.target.targets(), strict=True)]
        length = ca.norm_2(b - a)
        f = ca.sumsqr(ca.vertcat(*err)) / (SIGMA / MM) ** 2 + lim.length_weight * MM * length
        d = b - a
        g = []
        for i in range(n):
            pi = spheres[i, :].T
            t = ca.fmin(ca.fmax(ca.dot(pi - a, d) / ca.sumsqr(d), 0), 1)
            g += [ca.sumsqr(pi - a - t * d), ca.sumsqr(pi - a), ca.sumsqr(pi - b)]
        g.append(ca.sumsqr(d))
        g = ca.vertcat(*g)
        self._g_lb = np.array([(lim.min_gap / MM) ** 2, (lim.end_clearance / MM) ** 2,
                               (lim.end_clearance / MM) ** 2] * n + [(lim.min_length / MM) ** 2])
        self._g_ub = np.array([np.inf] * (3 * n) + [(lim.max_length / MM) ** 2])
        x0, y0, x1, y1 = (v / MM for v in lim.field)
        self._x_lb, self._x_ub = np.array([x0, y0, x0, y0]), np.array([x1, y1, x1, y1])
        self.objective = ca.Function("objective", [x, prm], [f]).expand()
        self.gradient = ca.Function("gradient", [x, prm], [ca.gradient(f, x)])
        nlp = {"x": x, "p": prm, "f": f, "g": g}
        opts = {"expand": True, "ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes",
                "ipopt.max_iter": self.max_iter, "ipopt.tol": 1e-6, "ipopt.acceptable_tol": 1e-4}
        solver = ca.nlpsol("assembly_pass", "ipopt", nlp, opts)
        batch = self._batch(ca.Function("constraints", [x, prm], [g]).expand())
        lib = None
        if compiled is not False:
            derivatives = [solver.get_function(k) for k in _DERIVATIVES]
            lib = compile_functions(f"assembly_{self.target.name}_{n}", [batch, *derivatives])
            if lib is None and compiled:
                raise MagctlError("assembly planner: compiled=True, but casadi's generated code could not be built "
                                  "(no C compiler found, or it failed)")
        self.compiled = lib is not None
        if lib is not None:
            solver = ca.nlpsol("assembly_pass", "ipopt", nlp, {**opts, **{o: lib[k] for k, o in _DERIVATIVES.items()}})
            batch = lib[batch.name()]
        self.solver, self._sample_batch = solver, batch

    def _batch(self, constraints: ca.Function) -> ca.Function:
        """The first stage in one call: the sampled passes built from the sphere centres (``(4, S)``, mm; by
        sphere, side (+, −), gap and direction), and the objective and constraints of the problem above mapped
        over them: each sample's cost where it keeps the bounds, infinite where it does not (a short-circuit
        ``if_else``: the objective is evaluated only for the samples that keep them). The samples are built
        here rather than handed in, and only the cost row is read back, because moving a ``(4, S)`` array
        between numpy and casadi costs more than evaluating the bounds on it."""
        n, dirs, gaps = self.target.n, self.directions, self.sample_gaps
        ang = 2 * np.pi * np.arange(dirs) / dirs
        u = np.stack([np.cos(ang), np.sin(ang)])                                     # (2, D)
        nrm = np.stack([-u[1], u[0]])
        offset = (np.array([1.0, -1.0])[:, None] * gaps / MM).ravel()                # (2·G,): side, gap
        along = np.tile(self.behind / MM * u, (1, n * offset.size))                  # (2, S), S = N·2·G·D
        across = np.tile((offset[:, None, None] * nrm.T[None]).reshape(-1, 2).T, (1, n))
        which = np.repeat(np.arange(n), offset.size * dirs)
        pick = ca.DM(ca.Sparsity.triplet(n, which.size, which.tolist(), list(range(which.size))), 1.0)

        prm = ca.MX.sym("p", 2 * n + 1)
        line = ca.mtimes(ca.reshape(prm[: 2 * n], 2, n), pick) + across              # the sphere, then the gap
        samples = ca.vertcat(line - along, line + along)

        x, p = ca.MX.sym("x", 4), ca.MX.sym("p", 2 * n + 1)
        g = constraints(x, p)
        tol = FEASIBLE_TOL / MM
        upper = np.flatnonzero(np.isfinite(self._g_ub))
        slack = ca.vertcat(g - (np.sqrt(self._g_lb) - tol) ** 2,            # squared distances, the bound less tol
                           (np.sqrt(self._g_ub[upper]) + tol) ** 2 - g[upper.tolist()],
                           x - (self._x_lb - tol), (self._x_ub + tol) - x)
        ok = ca.mmin(slack) >= 0
        one = ca.Function("pass_sample", [x, p], [ca.if_else(ok, self.objective(x, p), np.inf, True)])
        cost = one.map("pass_sample_map", "serial", which.size, [1], [])(samples, prm)
        return ca.Function("pass_samples", [prm], [samples, cost])

    def _parameters(self, spheres, mobility: float) -> np.ndarray:
        return np.r_[np.asarray(spheres, float).ravel() / MM, mobility]

    # --- sampling, refinement ----------------------------------------------------------------------
    def _sampled(self, prm) -> tuple[ca.DM, np.ndarray]:
        """The samples ``(4, S)`` (a, b in mm; casadi) and their costs (infinite where a bound is broken)."""
        samples, cost = self._sample_batch(prm)
        return samples, np.asarray(cost).ravel()

    def sample_costs(self, spheres, mobility: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Sampled passes ``(S, 2, 2)`` (start, end; m) round every sphere, their costs (infinite where a bound
        is broken) and which keep the bounds — one mapped evaluation of the problem."""
        spheres = np.asarray(spheres, float).reshape(self.target.n, 2)
        samples, cost = self._sampled(self._parameters(spheres, mobility))
        return np.asarray(samples).T.reshape(-1, 2, 2) * MM, cost, np.isfinite(cost)

    def samples(self, spheres) -> tuple[np.ndarray, np.ndarray]:
        """Sampled passes ``(S, 2, 2)`` (start, end; m) round every sphere and which keep the bounds."""
        cand, _, ok = self.sample_costs(spheres)
        return cand, ok

    @staticmethod
    def ranked(costs) -> np.ndarray:
        """Indices of ``costs`` from the lowest; costs equal but for rounding (:data:`TIE`) in their own order."""
        costs = np.asarray(costs, float)
        order = np.argsort(costs, kind="stable")
        c = costs[order]
        group = np.cumsum(np.r_[True, np.diff(c) > TIE * np.maximum(1.0, np.abs(c[1:]))])
        return order[np.lexsort((order, group))]

    def cost(self, spheres, a, b, mobility: float = 1.0) -> float:
        """The objective of the pass ``a → b`` (m) for spheres ``(N, 2)`` (m)."""
        return float(self.objective(np.r_[np.asarray(a, float), np.asarray(b, float)] / MM,
                                    self._parameters(spheres, mobility)))

    def plan(self, spheres, mobility: float = 1.0) -> Pass | None:
        """The next pass for spheres ``(N, 2)`` (m), or None when no sampled pass keeps the bounds.

        The ``starts`` best samples are refined with IPOPT; the best refined pass that keeps the bounds is
        returned if it beats the best sample (by more than :data:`SAME_COST`), else that sample. (Skipping a start
        beside one already refined saved solves on the earlier plant's map, but on the one plant's map it changed
        the assemblies of three of the four study layouts, so every start is refined.)
        """
        t0 = time.perf_counter()
        spheres = np.asarray(spheres, float).reshape(self.target.n, 2)
        prm = self._parameters(spheres, mobility)
        samples, costs = self._sampled(prm)
        feasible = np.flatnonzero(np.isfinite(costs))
        self.profile = {"samples": len(costs), "feasible": len(feasible), "ipopt_solves": 0, "ipopt_iterations": 0}
        if not len(feasible):
            self.profile.update(sample_s=time.perf_counter() - t0, ipopt_s=0.0, predict_s=0.0)
            return None
        order = feasible[self.ranked(costs[feasible])]
        t1 = time.perf_counter()
        top = [samples[:, int(k)].full().ravel() for k in order[: max(self.starts, 1)]]
        best_x, best_f, how = top[0], float(costs[order[0]]), "sample"
        refined, iterations = [], 0
        for x0 in top[: self.starts]:
            refined.append(x0)
            sol = self.solver(x0=x0, p=prm, lbx=self._x_lb, ubx=self._x_ub, lbg=self._g_lb, ubg=self._g_ub)
            iterations += int(self.solver.stats()["iter_count"])
            x = np.asarray(sol["x"], float).ravel()
            f = float(sol["f"])
            if (f < best_f - SAME_COST * max(1.0, abs(best_f))
                    and self.limits.violation(spheres, x[:2] * MM, x[2:] * MM) <= 1e-7):
                best_x, best_f, how = x, f, "ipopt"
        t2 = time.perf_counter()
        a, b = best_x[:2] * MM, best_x[2:] * MM
        predicted = spheres + mobility * self.map.displacement(spheres, a, b)
        t3 = time.perf_counter()
        self.profile.update(ipopt_solves=len(refined), ipopt_iterations=iterations, sample_s=t1 - t0,
                            ipopt_s=t2 - t1, predict_s=t3 - t2)
        return Pass(a, b, predicted, best_f, float(self.target.error(predicted)), how, t3 - t0)


class GreedyPlanner:
    """The baseline: the paper's side push extended one sphere at a time (θ_n, eq 17 with ``exp-fit``)."""

    def __init__(self, target: Arrangement, *, theta_n: float | None = None, model=None):
        p = with_defaults("assembly", theta_n=theta_n)
        side = with_defaults("side", min_gap=None, behind=None, ahead=None)
        self.target = target
        self.theta_n = float(p["theta_n"])
        self.model = side_model("exp-fit") if model is None else model
        self.min_gap, self.behind, self.ahead = float(side["min_gap"]), float(side["behind"]), float(side["ahead"])
        self.d_max = float(self.model.displacement(self.min_gap))

    def stage(self, spheres) -> int:
        """The first sphere not yet where the arrangement puts it (its bonds to the earlier ones kept)."""
        t, p = self.target, np.asarray(spheres, float)
        dist = t.distances(p)
        for k in range(1, t.n):
            rows = np.flatnonzero(t.bonds[:, 1].astype(int) == k)
            rows = rows[t.bonds[rows, 0].astype(int) < k]
            ok = np.where(t.contact[rows], dist[rows] <= t.bonds[rows, 2] + t.eps_as,
                          dist[rows] >= t.bonds[rows, 2] * np.cos(t.bend / 2))
            if not ok.all():
                return k
        return t.n - 1

    def plan(self, spheres, robot) -> Pass:
        t0 = time.perf_counter()
        p = np.asarray(spheres, float)
        k = self.stage(p)
        s, goal = p[k], self.target.placement(p, k)
        v = goal - s
        dist = float(np.hypot(*v))
        v = v / max(dist, 1e-12)
        if self.target.name == "pair":  # eq 21: what remains is the surface gap
            dist = max(float(np.hypot(*(p[1] - p[0]))) - 2 * self.target.radius, 0.0)
        n_v = np.array([-v[1], v[0]])
        side = 1.0 if float(n_v @ (np.asarray(robot, float) - s)) >= 0 else -1.0
        c, sn = np.cos(side * self.theta_n), np.sin(side * self.theta_n)
        u = np.array([c * v[0] - sn * v[1], sn * v[0] + c * v[1]])   # eq 21's adjusted line, towards the robot
        gap = max(float(self.model.gap(min(dist, self.d_max))), self.min_gap) if dist > 0 else self.min_gap
        line = s + side * gap * np.array([-u[1], u[0]])
        a, b = line - self.behind * u, line + self.ahead * u
        return Pass(a, b, p, float("nan"), float(self.target.error(p)), "greedy", time.perf_counter() - t0)


PLANNERS = {"optimal": "passes optimised on the pass map with IPOPT (AssemblyPlanner)",
            "greedy": "the paper's side push one sphere at a time, theta_n = 30 deg (GreedyPlanner)"}


class PassPlanner(Block):
    """The planner as a block: stepped once per pass, it turns the tracked spheres into the next pass.

    Ports: inputs ``spheres`` (N, 2) m and ``robot`` (2,) m, the measurements after the last pass;
    outputs ``start``, ``end`` (2,) m, the pass, and ``y`` (m), its predicted RMS bond error.

    State: the pass, its prediction, the learned mobility (see the module docstring) and the passes planned.
    A trial with no feasible pass gets ``start = end = NaN`` (the task then stops it as stalled). The greedy
    baseline predicts nothing: its ``y`` is the bond error before the pass and it learns no mobility.
    """

    def __init__(self, target: Arrangement, name: str = "pass_planner", *, planner: str = "optimal", **kw):
        if planner not in PLANNERS:
            raise MagctlError(f"pass planner {name!r}: planner={planner!r} is not one of {', '.join(PLANNERS)}")
        self.target, self.kind = target, planner
        self.planner = AssemblyPlanner(target, **kw) if planner == "optimal" else GreedyPlanner(target, **kw)
        n = target.n
        super().__init__(name, inputs=[Port("spheres", (n, 2), "m"), Port("robot", (2,), "m")],
                         outputs=[Port("start", (2,), "m"), Port("end", (2,), "m"), Port("y", (), "m")],
                         dt=ATTEMPT, feedthrough=False)

    def state_vars(self):
        n = self.target.n
        return (StateVar("start", (2,), symbol="a", description="start of the planned pass, m"),
                StateVar("end", (2,), symbol="b", description="end of the planned pass, m"),
                StateVar("before", (n, 2), symbol="P", description="sphere centres the pass was planned on, m"),
                StateVar("predicted", (n, 2), symbol="P'", description="where the pass should leave them, m"),
                StateVar("error", (), description="predicted RMS bond error after the pass, m"),
                StateVar("mobility", (), symbol="m", description="measured over predicted displacement"),
                StateVar("weight", (), description="sum of squared predicted displacements so far, m²"),
                StateVar("passes", (), "int64", description="passes planned"))

    def initial_state(self, batch, rng=None):
        n = self.target.n
        return {"start": np.full((batch, 2), np.nan), "end": np.full((batch, 2), np.nan),
                "before": np.full((batch, n, 2), np.nan), "predicted": np.full((batch, n, 2), np.nan),
                "error": np.full(batch, np.nan), "mobility": np.ones(batch), "weight": np.zeros(batch),
                "passes": np.zeros(batch, dtype=np.int64)}

    def output(self, state, u):
        return {"start": state["start"], "end": state["end"], "y": state["error"]}

    def update(self, state, u):
        return self.update_where(state, u, np.ones(len(state["passes"]), bool))

    def learn(self, state, spheres) -> dict:
        """The mobility after the pass just made: least squares of measured on predicted displacement.

        ``m ← (W·m + Σ d_pred·d_meas) / (W + Σ |d_pred|²)``, the sums over the spheres of this pass, with
        ``W`` the larger of the squared predicted displacements of the passes so far and (10 µm)² — the prior
        ``m = 1`` counts as one 10 µm displacement until the passes outweigh it; clipped to [0.2, 3].
        """
        pred = state["predicted"] - state["before"]
        meas = np.asarray(spheres, float) - state["before"]
        ok = np.isfinite(pred).all(axis=(1, 2)) & np.isfinite(meas).all(axis=(1, 2))
        num = np.where(ok, np.einsum("bij,bij->b", np.nan_to_num(pred), np.nan_to_num(meas)), 0.0)
        den = np.where(ok, np.einsum("bij,bij->b", np.nan_to_num(pred), np.nan_to_num(pred)), 0.0)
        prior = np.maximum(state["weight"], SIGMA ** 2)
        m = np.clip((prior * state["mobility"] + num) / (prior + den), 0.2, 3.0)
        return {**state, "mobility": np.where(ok & (den > 0), m, state["mobility"]), "weight": state["weight"] + den}

    def update_where(self, state, u, mask) -> dict:
        """Learn from the pass just made and plan the next one, for the trials in ``mask``."""
        mask = np.asarray(mask, bool)
        spheres, robot = np.asarray(u["spheres"], float), np.asarray(u["robot"], float)
        new = {k: v.copy() for k, v in state.items()}
        if not mask.any():
            return new
        if self.kind == "optimal":
            learned = self.learn(state, spheres)
            new["mobility"] = np.where(mask, learned["mobility"], new["mobility"])
            new["weight"] = np.where(mask, learned["weight"], new["weight"])
        for b in np.flatnonzero(mask):
            if self.kind == "optimal":
                plan = self.planner.plan(spheres[b], float(new["mobility"][b]))
            else:
                plan = self.planner.plan(spheres[b], robot[b])
            if plan is None:
                new["start"][b] = new["end"][b] = np.nan
                continue
            new["start"][b], new["end"][b] = plan.start, plan.end
            new["before"][b], new["predicted"][b] = spheres[b], plan.predicted
            new["error"][b] = plan.error
        new["passes"] = new["passes"] + mask
        return new


__all__ = ["AssemblyPlanner", "GreedyPlanner", "Pass", "PassPlanner", "PlanLimits", "PLANNERS"]
