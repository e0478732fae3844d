"""Target arrangements of N spheres: which pairs must touch, which distances set the shape, when it is done.

An arrangement is a set of *bonds* ``(i, j, L_ij)``: the centre distances the assembled spheres must have,
independent of where the group lies or how it is turned. *Contact* bonds (``L = R_i + R_j``) are eq 21's
``|P_j − P_i| ≤ R_i + R_j + ε_as``; *shape* bonds (longer) fix the angles — a line of three has its ends
``4R`` apart, straight to within ``bend``: ``|P_2 − P_0| ≥ 4R·cos(bend/2)``.

=========  ===  ==========================================================
name       N    bonds
=========  ===  ==========================================================
pair       2    0–1 in contact (eq 21, the paper's §V-C)
line       3–4  consecutive spheres in contact, ends of every 3-run 4R apart
triangle   3    all three pairs in contact
=========  ===  ==========================================================
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magctl.core.errors import MagctlError

ARRANGEMENTS = {"pair": "two spheres in contact (eq 21)",
                "line": "three or four spheres in a straight chain, each touching the next",
                "triangle": "three spheres, each touching the other two"}
SIZES = {"pair": (2,), "line": (3, 4), "triangle": (3,)}


@dataclass(frozen=True)
class Arrangement:
    """A target arrangement of ``n`` spheres of radius ``radius`` (m).

    Attributes
    ----------
    name : str
        One of :data:`ARRANGEMENTS`.
    n : int
        Number of spheres.
    radius : float
        ``R`` (m), the same for every sphere (105 µm, §II).
    eps_as : float
        ``ε_as`` of eq 21 (m).
    bend : float
        Largest bend of a line from straight (rad) that still counts as a line.
    """

    name: str
    n: int
    radius: float
    eps_as: float
    bend: float

    def __post_init__(self):
        if self.name not in ARRANGEMENTS:
            raise MagctlError(f"arrangement {self.name!r} is not one of {', '.join(ARRANGEMENTS)}")
        if self.n not in SIZES[self.name]:
            raise MagctlError(f"arrangement {self.name!r} takes {' or '.join(map(str, SIZES[self.name]))} spheres, "
                              f"not {self.n}")
        if not (self.radius > 0 and self.eps_as >= 0 and 0 <= self.bend < np.pi / 2):
            raise MagctlError(f"arrangement {self.name!r}: radius > 0, eps_as >= 0 and bend in [0, 90°) needed")

    @property
    def bonds(self) -> np.ndarray:
        """``(K, 3)``: ``i, j, L_ij`` (m) of every bond, contact bonds first."""
        d = 2 * self.radius
        if self.name == "pair":
            rows = [(0, 1, d)]
        elif self.name == "triangle":
            rows = [(0, 1, d), (1, 2, d), (0, 2, d)]
        else:
            rows = [(i, i + 1, d) for i in range(self.n - 1)] + [(i, i + 2, 2 * d) for i in range(self.n - 2)]
            if self.n == 4:
                rows.append((0, 3, 3 * d))
        return np.array(rows, dtype=float)

    @property
    def contact(self) -> np.ndarray:
        """Which bonds are contacts (eq 21) rather than shape distances."""
        return np.isclose(self.bonds[:, 2], 2 * self.radius)

    def targets(self) -> np.ndarray:
        """Bond lengths the planner aims at: contacts at ``2R + ε_as/2`` (mid-tolerance), shapes at ``L``."""
        return np.where(self.contact, self.bonds[:, 2] + self.eps_as / 2, self.bonds[:, 2])

    def distances(self, spheres) -> np.ndarray:
        """Bond lengths ``(…, K)`` of sphere positions ``(…, N, 2)``."""
        p = np.asarray(spheres, float)
        i, j = self.bonds[:, 0].astype(int), self.bonds[:, 1].astype(int)
        return np.linalg.norm(p[..., j, :] - p[..., i, :], axis=-1)

    def assembled(self, spheres) -> np.ndarray:
        """Eq 21 on every contact bond and the shape bonds within ``bend``: bool ``(…)``."""
        dist = self.distances(spheres)
        ok = np.where(self.contact, dist <= self.bonds[:, 2] + self.eps_as,
                      dist >= self.bonds[:, 2] * np.cos(self.bend / 2))
        return np.all(ok, axis=-1)

    def error(self, spheres) -> np.ndarray:
        """RMS bond error ``(…)`` against :meth:`targets` (m): the planner's objective, as a number."""
        return np.sqrt(np.mean((self.distances(spheres) - self.targets()) ** 2, axis=-1))

    def placement(self, spheres, k: int) -> np.ndarray:
        """Where sphere ``k`` belongs given spheres ``0..k−1`` where they lie (the greedy order), ``(…, 2)``.

        Sphere 0 stays where it is; a pair's sphere 1 touches sphere 0 on their centre line; a line's sphere
        ``k`` extends the chain beyond ``k − 1`` (its centre line with ``k − 2``; for ``k`` = 1 towards where
        sphere 1 lies); a triangle's sphere 2 is the apex on its own side of the 0–1 bond.
        """
        p = np.asarray(spheres, float)
        d = 2 * self.radius + self.eps_as / 2
        if k == 0:
            return p[..., 0, :]
        if k == 1 or (self.name == "line" and k >= 1):
            base = p[..., k - 1, :]
            ref = p[..., k, :] if k == 1 else 2 * base - p[..., k - 2, :]
            v = ref - base
            return base + d * v / np.linalg.norm(v, axis=-1, keepdims=True)
        # triangle apex
        a, b, c = p[..., 0, :], p[..., 1, :], p[..., 2, :]
        mid, v = (a + b) / 2, b - a
        n = np.stack([-v[..., 1], v[..., 0]], axis=-1) / np.linalg.norm(v, axis=-1, keepdims=True)
        side = np.sign(np.einsum("...i,...i->...", c - mid, n))[..., None]
        side = np.where(side == 0, 1.0, side)
        return mid + side * n * np.sqrt(d ** 2 - (np.linalg.norm(v, axis=-1, keepdims=True) / 2) ** 2)


def arrangement(name: str, n: int | None = None, *, eps_as: float | None = None, bend: float | None = None,
                radius: float | None = None) -> Arrangement:
    """The arrangement ``name`` of ``n`` spheres (default: the smallest it takes), tolerances from
    ``models/push.toml`` ``[assembly]`` and ``[plan]``, radius from ``models/sphere.toml``."""
    from magctl.config import load_model

    if name not in ARRANGEMENTS:
        raise MagctlError(f"arrangement {name!r} is not one of {', '.join(ARRANGEMENTS)}")
    push = load_model("push")
    n = SIZES[name][0] if n is None else int(n)
    return Arrangement(name, n, float(load_model("sphere").sphere.radius) if radius is None else float(radius),
                       float(push.assembly.eps_as) if eps_as is None else float(eps_as),
                       float(push.plan.bend) if bend is None else float(bend))


__all__ = ["ARRANGEMENTS", "Arrangement", "arrangement"]
