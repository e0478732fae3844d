"""A minimal kinematic stand-in for robot + spheres + camera + tracker, for push-task tests.

The robot point moves straight to its target at ``min(speed_cap, v_max)``. A sphere the
robot runs into is pushed ahead at the contact distance; when the robot then moves
away it pulls the sphere after it by a random ``D_p,r ~ N(300, 75²) µm`` (§IV-D). A
robot passing a sphere at lateral distance ``D_g`` (between contact and ``side_range``)
displaces it ``1755·exp(−0.009042·D_g) µm`` (eq 22) along its motion when it crosses
the sphere's abeam line on a straight path (orbiting round a sphere does not count). Overlapping
spheres are separated by moving the one that was not pushed.
"""

from __future__ import annotations

import numpy as np

from magctl import FRAME_PERIOD_S
from magctl.core.block import Block
from magctl.core.ports import Port

UM = 1e-6


def _norm(v):
    return np.sqrt(np.einsum("...i,...i->...", v, v))


class StandInPlant(Block):
    def __init__(self, robot0, spheres0, *, v_max=1e-3, contact=250 * UM, side_range=800 * UM,
                 release_mean=300 * UM, release_std=75 * UM, radius=105 * UM, lost_from=None, sphere_lost_from=None):
        self.robot0 = np.asarray(robot0, float)
        self.spheres0 = np.asarray(spheres0, float)
        n = self.spheres0.shape[-2]
        self.v_max, self.contact, self.side_range = v_max, contact, side_range
        self.release_mean, self.release_std, self.radius = release_mean, release_std, radius
        self.lost_from, self.sphere_lost_from = lost_from, sphere_lost_from
        super().__init__(
            "plant",
            inputs=[Port("target", (2,), "m"), Port("speed_cap", (), "m/s")],
            outputs=[Port("robot_est", (2,), "m"), Port("spheres_est", (n, 2), "m"), Port("lost", (), "1", "bool"),
                     Port("releases", (), "1"), Port("last_release", (), "m")],
            feedthrough=False,
        )

    @property
    def uses_random(self):
        return True

    def initial_state(self, batch, rng=None):
        n = self.spheres0.shape[-2]
        return {"r": np.broadcast_to(self.robot0, (batch, 2)).copy(),
                "s": np.broadcast_to(self.spheres0, (batch, n, 2)).copy(),
                "attached": np.zeros((batch, n), bool), "pending": np.zeros((batch, n)),
                "count": np.zeros(batch), "last": np.zeros(batch), "tick": 0, "rng": rng,
                "prev_dir": np.zeros((batch, 2)), "passed": np.zeros((batch, n), bool)}

    def output(self, st, u):
        b = st["r"].shape[0]
        lost = np.full(b, self.lost_from is not None and st["tick"] >= self.lost_from)
        s = st["s"].copy()
        if self.sphere_lost_from is not None and st["tick"] >= self.sphere_lost_from:
            s[:] = np.nan
        return {"robot_est": st["r"].copy(), "spheres_est": s, "lost": lost, "releases": st["count"].copy(),
                "last_release": st["last"].copy()}

    def update(self, st, u):
        draw = st["rng"].standard_normal(())
        r, s = st["r"], st["s"]
        d = u["target"] - r
        dist = _norm(d)
        cap = np.where(u["speed_cap"] > 0, np.minimum(u["speed_cap"], self.v_max), 0.0)
        frac = np.minimum(1.0, cap * FRAME_PERIOD_S / np.where(dist > 0, dist, 1.0))
        step = d * frac[:, None]
        size = _norm(step)
        moving = size > 1e-12
        dirn = np.where(moving[:, None], step / np.where(moving, size, 1.0)[:, None], 0.0)
        r_new = r + step
        # eq 22 is the displacement of a straight pass: count crossings only on a straight path
        straight = np.einsum("bi,bi->b", dirn, st["prev_dir"]) > np.cos(np.deg2rad(1.0))
        st["prev_dir"] = dirn
        st["passed"] &= straight[:, None]  # one eq 22 displacement per straight pass
        n = s.shape[1]
        pushed = np.zeros((r.shape[0], n), bool)
        for j in range(n):
            sj = s[:, j]
            rel_old, rel = sj - r, sj - r_new
            a_old = np.einsum("bi,bi->b", rel_old, dirn)
            a_new = np.einsum("bi,bi->b", rel, dirn)
            lat = np.abs(dirn[:, 0] * rel_old[:, 1] - dirn[:, 1] * rel_old[:, 0])
            # side pass (eq 22)
            cross_ = (moving & straight & ~st["passed"][:, j] & (a_old > 0) & (a_new <= 0) & (lat > self.contact)
                      & (lat < self.side_range))
            st["passed"][:, j] |= cross_
            sj = sj + (cross_ * 1755 * UM * np.exp(-0.009042 / UM * lat))[:, None] * dirn
            # release on retraction: the sphere follows the robot for D_p,r
            rel = sj - r_new
            away = moving & (np.einsum("bi,bi->b", rel, dirn) < 0)
            rel_now = st["attached"][:, j] & away
            amount = np.maximum(0.0, self.release_mean + self.release_std * draw)
            st["pending"][:, j] = np.where(rel_now, amount, st["pending"][:, j])
            st["count"] = st["count"] + rel_now
            st["last"] = np.where(rel_now, amount, st["last"])
            st["attached"][:, j] &= ~rel_now
            follow = np.where(away, np.minimum(st["pending"][:, j], size), 0.0)
            sj = sj + follow[:, None] * dirn
            st["pending"][:, j] -= follow
            # contact push
            rel = sj - r_new
            along = np.einsum("bi,bi->b", rel, dirn)
            lat_now = np.abs(dirn[:, 0] * rel[:, 1] - dirn[:, 1] * rel[:, 0])
            reach = np.sqrt(np.maximum(self.contact**2 - lat_now**2, 0.0))
            push = moving & (along > -1e-12) & (lat_now < self.contact) & (along < reach)
            sj = sj + (push * (reach - along))[:, None] * dirn
            st["attached"][:, j] |= push
            st["pending"][:, j] = np.where(push, 0.0, st["pending"][:, j])
            pushed[:, j] = push | (follow > 0)
            s[:, j] = sj
        # sphere-sphere overlap: move the sphere that was not driven
        for i in range(n):
            for j in range(i + 1, n):
                sep = s[:, j] - s[:, i]
                dd = _norm(sep)
                over = dd < 2 * self.radius
                if over.any():
                    v = sep / np.where(dd > 0, dd, 1.0)[:, None]
                    fix = (2 * self.radius - dd) * over
                    move_j = ~pushed[:, j]
                    s[:, j] += np.where(move_j, fix, 0.0)[:, None] * v
                    s[:, i] -= np.where(move_j, 0.0, fix)[:, None] * v
        st["r"] = r_new
        st["s"] = s
        st["tick"] += 1
        return st
