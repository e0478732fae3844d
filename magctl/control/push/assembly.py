"""Two-sphere assembly (§V-C, eq 21) by side pushing, and the front-push variant (Fig 3).

Side-push assembly, per attempt: the *adjusted line* leaves sphere 1 at ``θ_n`` to the
line sphere 1 → sphere 2, turned towards the side the robot is on; the *motion line*
is parallel to it at the gap ``D_g`` (eq 17 with ``D_s,des`` the distance still to
close, bounded); the robot passes along it, side-pushing sphere 1 towards sphere 2 and
diverging from sphere 2. Repeat until eq 21: ``|P_s2 − P_s1| ≤ R_1 + R_2 + ε_as``.
"""

from __future__ import annotations

import numpy as np

from magctl.control.push.common import sphere_radii, with_defaults
from magctl.control.push.front import FrontAssemblyTask
from magctl.control.push.side import SidePushTask
from magctl.core.batched import cross, norm, rotate, unit
from magctl.core.checks import check_positive
from magctl.core.errors import MagctlError


class AssemblyTask(SidePushTask):
    """Side-push assembly of sphere ``moved`` onto sphere ``fixed`` (eq 21).

    Parameters
    ----------
    theta_n : float
        Angle of the adjusted line (rad); the paper's experiment used 30° (§VI-C).
    radii : (float, float)
        ``R_1``, ``R_2`` (m); 105 µm for the 210 µm spheres (§II).
    eps_as : float
        ``ε_as`` of eq 21 (m).
    **kw
        Everything :class:`SidePushTask` takes (``ks``, ``model``, ``law``, ``fixed_gap``,
        ``max_attempts`` …); ``goal`` is not used.
    """

    def __init__(self, name: str = "assembly", *, n_spheres: int = 2, moved: int = 0, fixed: int = 1,
                 theta_n: float | None = None, radii=None, eps_as: float | None = None, **kw):
        if moved == fixed or not (0 <= moved < n_spheres and 0 <= fixed < n_spheres):
            raise MagctlError(f"assembly {name!r}: sphere indices {moved}, {fixed} must differ and be < {n_spheres}")
        p = with_defaults("assembly", theta_n=theta_n, eps_as=eps_as, ks=kw.pop("ks", None))
        theta = float(p["theta_n"])
        if not 0 <= theta < np.pi / 2:
            raise MagctlError(f"assembly {name!r}: theta_n={theta!r} rad must be in [0, pi/2)")
        self.theta_n = theta
        radii = sphere_radii() if radii is None else radii
        self.radii = (check_positive("radius 1", radii[0]), check_positive("radius 2", radii[1]))
        self.eps_as = check_positive("eps_as", p["eps_as"], allow_zero=True)
        kw["ks"] = p["ks"]
        super().__init__(name, n_spheres=n_spheres, sphere=moved, **kw)
        self.sphere_indices = (int(moved), int(fixed))

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


__all__ = ["AssemblyTask", "FrontAssemblyTask"]
