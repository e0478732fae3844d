"""The front push's model of its own release: the map identified from the closed loop, and the controller on it.

:class:`ReleaseMap` is the release's conditional distribution identified from logged closed-loop attempts
(``models/front_release.toml``, written by :mod:`magctl.studies.front_release`): the attempt map of
:mod:`magctl.stability.iteration` samples it as a plant, and :class:`ReleasePolicyLaw` uses it as the
controller's model.

The release-model controller (docs/push-control.md §7): before each attempt it picks the ``δ`` that
maximises the chance of ending within ε_p (eq 12) given what it can see — the distance ``d`` to the goal
and the trial's last release ``R_prev``:

    δ*(d, R_prev) = argmax_δ P( |(R − δ, lateral)| < ε_p  |  L = d + δ, R_prev ),

the probability read as the share of the ``k`` logged later attempts nearest to ``(d + δ, R_prev)`` that
would have ended inside; the first attempt chooses among the logged first pushes (the map has first
releases at those push lengths only). :class:`ReleasePolicyLaw` is that controller as a learning-law block:
it takes eq 13's place in :class:`~magctl.control.push.front.FrontPushTask` (``learning="release"``).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.spatial import cKDTree

from magctl.config import load_model
from magctl.control.learning import ATTEMPT, AttemptLaw
from magctl.core.block import Block, StateVar
from magctl.core.checks import check_positive
from magctl.core.errors import MagctlError
from magctl.core.ports import Port
from magctl.core.units import UM

DELTAS = np.arange(-200.0, 401.0, 10.0) * UM
"""Candidate ``δ`` of the policy (m): the span of the logged push lengths minus the goal distances."""
MAP_NEIGHBOURS = 15
"""Logged later attempts a draw of the release map chooses among (``k`` of its k-nearest-neighbour resampling)."""
MAP_SCALE = 100 * UM
"""Length that scales both predictors (push length, previous release) of the map's neighbour search."""
NEIGHBOURS = 2 * MAP_NEIGHBOURS
"""Logged later attempts whose outcomes estimate one candidate's success (twice the map's resampling k)."""


@dataclass(frozen=True)
class ReleaseMap:
    """The front push's release map identified from the closed loop: a conditional distribution (metres).

    Stored in ``models/front_release.toml`` by :mod:`magctl.studies.front_release`: every logged
    attempt of the identification trials with its predictors — the push length ``L = e_before + δ``
    (how far the sphere has to go to ``P_o``, eq 10) and the previous attempt's release ``R_prev``
    — and its outcome: the release ``R = e_after + δ`` (how far short of ``P_o`` the sphere is
    measured), its distance off the pushing line and whether the robot touched it.

    :meth:`sample` draws the outcome of a logged attempt near the query (k-nearest-neighbour
    conditional resampling): a first attempt from the logged first attempts at the nearest logged
    push length (the first push starts from rest; its ``L`` is the goal distance plus ``δ(0)``),
    a later one uniformly from the ``k`` logged later attempts nearest in ``(L, R_prev)`` (both
    scaled by ``scale``). The outcome is drawn jointly: ``R``, the lateral distance and contact
    keep their dependence. The paper's eq 14 plant is the special case of outcomes
    ``R ~ N(300, 75²) µm`` independent of ``(L, R_prev)``, no lateral distance.
    """

    first: np.ndarray
    length: np.ndarray
    previous: np.ndarray
    release: np.ndarray
    lateral: np.ndarray
    contact: np.ndarray
    k: int = MAP_NEIGHBOURS
    scale: float = MAP_SCALE
    source: str = ""

    @classmethod
    def load(cls, name: str = "front_release") -> ReleaseMap:
        """Read ``models/<name>.toml`` (written by ``magctl.studies.front_release.write_model``)."""
        p = load_model(name)
        m = p.map
        return cls(np.asarray(m.first, float) > 0.5, np.asarray(m.length, float), np.asarray(m.previous, float),
                   np.asarray(m.release, float), np.asarray(m.lateral, float), np.asarray(m.contact, float) > 0.5,
                   int(m.neighbours), float(m.scale), p.provenance.sources["trials"])

    def __post_init__(self):
        n = self.first.size
        for name in ("length", "previous", "release", "lateral", "contact"):
            a = getattr(self, name)
            if a.shape != (n,) or (a.dtype.kind == "f" and not np.all(np.isfinite(a))):
                raise MagctlError(f"release map {name} needs {n} finite entries, got shape {a.shape}")
        n_later = int((~self.first).sum())
        if not self.first.any() or n_later < self.k or self.k < 1:
            raise MagctlError(f"release map needs first attempts and at least k = {self.k} later ones "
                              f"(has {int(self.first.sum())} and {n_later})")
        if not self.scale > 0:
            raise MagctlError(f"release map scale {self.scale!r} must be positive")

    @cached_property
    def _later(self):
        idx = np.flatnonzero(~self.first)
        return cKDTree(np.c_[self.length[idx], self.previous[idx]] / self.scale), idx

    @cached_property
    def _first(self):
        idx = np.flatnonzero(self.first)
        values, group = np.unique(self.length[idx], return_inverse=True)
        return values, [idx[group == g] for g in range(values.size)]

    def sample(self, length, first, rng: np.random.Generator, previous=None
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Draw ``(R, lateral, contact)`` for each push length (``first``: bool, per draw or one for all).

        ``previous`` is each trial's previous release (required for later attempts).
        """
        length = np.atleast_1d(np.asarray(length, float))
        n = length.size
        first = np.broadcast_to(np.asarray(first, bool), (n,))
        pick = np.zeros(n, dtype=int)
        if first.any():
            values, groups = self._first
            g = np.abs(length[first, None] - values[None, :]).argmin(axis=1)
            rows = np.flatnonzero(first)
            for gi in np.unique(g):
                sel = rows[g == gi]
                pick[sel] = groups[gi][rng.integers(0, groups[gi].size, sel.size)]
        if not first.all():
            if previous is None:
                raise MagctlError("release map: later attempts need the previous release")
            prev = np.broadcast_to(np.asarray(previous, float), (n,))[~first]
            tree, idx = self._later
            _, nb = tree.query(np.c_[length[~first], prev] / self.scale, k=self.k)
            nb = nb.reshape(-1, self.k)
            pick[~first] = idx[nb[np.arange(nb.shape[0]), rng.integers(0, self.k, nb.shape[0])]]
        return self.release[pick], self.lateral[pick], self.contact[pick]


@dataclass(frozen=True)
class ReleasePolicy:
    """The greedy release-model controller: ``δ(0)`` for the first attempt, ``δ*(d, R_prev)`` after it.

    A candidate's success is read on the ``k`` logged later attempts nearest its query — nearest by the scaled
    distance, and among logged attempts as near as the k-th, the earlier in the map first, so the choice does not
    depend on how a search structure orders ties (the map holds repeated predictors); the first best candidate is
    taken where several are as good. The law's kernel (:func:`magctl.control.kernels.release_choose`) searches
    :meth:`kernel_tables` by that rule.
    """

    delta0: float
    first_success: dict[float, float]
    """Share of logged first attempts ending within ε_p, by first push length (m)."""
    deltas: np.ndarray
    tree: cKDTree
    rows: np.ndarray
    release_map: ReleaseMap
    eps: float
    k: int

    @cached_property
    def points(self) -> np.ndarray:
        """The logged later attempts' ``(L, R_prev) / scale``, as the tree holds them (row ``i`` is map row
        ``rows[i]``)."""
        return np.asarray(self.tree.data)

    @cached_property
    def hits(self) -> np.ndarray:
        """``(len(deltas), len(rows))``: whether each logged later attempt would have ended within ε_p had it been
        pushed with each candidate ``δ``: ``|(R − δ, lateral)| < ε_p``."""
        m = self.release_map
        return np.hypot(m.release[self.rows][None, :] - self.deltas[:, None], m.lateral[self.rows][None, :]) < self.eps

    def kernel_tables(self) -> tuple:
        """``(scale, deltas, xs0, xs1, srow, hits)`` of the compiled law
        (:func:`magctl.control.kernels.release_choose`): the logged later attempts sorted by scaled push length (a
        stable sort), their map rows, and :attr:`hits` in that order."""
        order = np.argsort(self.points[:, 0], kind="stable")
        return (float(self.release_map.scale), np.ascontiguousarray(self.deltas, dtype=float),
                np.ascontiguousarray(self.points[order, 0]), np.ascontiguousarray(self.points[order, 1]),
                np.ascontiguousarray(self.rows[order], dtype=np.int64), np.ascontiguousarray(self.hits[:, order]))


def release_policy(release_map: ReleaseMap, *, eps: float, goal: float, deltas=DELTAS,
                   k: int = NEIGHBOURS) -> ReleasePolicy:
    """The greedy controller of the module docstring, estimated from ``release_map`` (ε_p ``eps`` and the first
    attempt's goal distance ``goal``, m)."""
    check_positive("eps", eps)
    later = np.flatnonzero(~release_map.first)
    if later.size < k or k < 1:
        raise MagctlError(f"release policy needs at least k = {k} later attempts, the map has {later.size}")
    m = release_map
    first = {}
    for length in np.unique(m.length[m.first]):
        sel = m.first & (m.length == length)
        delta = length - goal
        first[float(length)] = float((np.hypot(m.release[sel] - delta, m.lateral[sel]) < eps).mean())
    best_length = max(first, key=first.get)
    tree = cKDTree(np.c_[m.length[later], m.previous[later]] / m.scale)
    return ReleasePolicy(best_length - goal, first, np.asarray(deltas, float), tree, later, m, float(eps), int(k))


class ReleasePolicyLaw(AttemptLaw, Block):
    """The release-model controller as the front push's learning law (in eq 13's place).

    State ``δ`` (eq 10's offset of ``P_o``) and the map rows it was last read on. After an attempt that ended with
    along-line error ``e = (P_g − P_s)·u`` the release was ``R = e + δ`` and the next attempt starts ``|e|`` from
    the goal, so ``δ ← δ*(|e|, e + δ)`` (:class:`ReleasePolicy`, success = eq 12 within ε_p; a non-finite ``e``
    keeps ``δ``). Initial ``δ`` is the policy's ``δ(0)``.

    Ports: input ``e`` () m, output ``y`` () = ``δ`` m — those of :class:`~magctl.control.learning.LearningLaw`,
    so :class:`~magctl.control.push.front.FrontPushTask` steps either.
    """

    def __init__(self, name: str, policy: ReleasePolicy, dt: float = ATTEMPT):
        self.policy = policy
        super().__init__(name, inputs=[Port("e", (), "m")], outputs=[Port("y", (), "m")], dt=dt, feedthrough=False)

    def state_vars(self):
        return (StateVar("x", (), symbol="δ", description="the next attempt's δ, m"),
                StateVar("neighbours", (self.policy.k,), "int64",
                         description="map rows of the logged attempts the last δ was read on, nearest first "
                                     "(−1 before the first)"))

    def initial_state(self, batch, rng=None):
        return {"x": np.full(batch, self.policy.delta0), "neighbours": np.full((batch, self.policy.k), -1)}

    def kernel(self):
        """The law (:func:`magctl.control.kernels.release_output`, ``release_update_step``): ``y = δ``, then
        ``δ ← δ*(|e|, e + δ)`` and the map rows it was read on."""
        from magctl.control import kernels as k
        from magctl.core.kernel import Kernel

        return Kernel(output=k.release_output, update=k.release_update_step, params=self.policy.kernel_tables())


def release_policy_law(name: str = "front_law", *, eps: float, goal: float) -> ReleasePolicyLaw:
    """The law on the identified map of ``models/front_release.toml``."""
    return ReleasePolicyLaw(name, release_policy(ReleaseMap.load(), eps=eps, goal=goal))
