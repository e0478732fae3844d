"""Numpy references of the plant blocks: the coil actuator, the drive, the stick-slip robot and the fused
drive → coils → robot block, the Spheres block's array frame, and the kinematic stand-in's blocks.

The library runs each of them by its kernel (:mod:`magctl.plant.kernels`, :mod:`magctl.plant.sphere_kernel`,
:mod:`magctl.plant.standin_kernels`); these are the batched numpy forms the kernels were written from and are
tested against. Physics helpers that library code calls itself stay in the library and are used from here
(``Spheres._capped``/``_gap_rate``, kept for :meth:`~magctl.plant.sphere.Spheres.sphere_velocity`;
:func:`~magctl.plant.sphere.separate_spheres`, which places the spheres at step 0;
:meth:`~magctl.plant._coilfield.CoilAllocation.static_currents`, the rig's allocation).
"""

from __future__ import annotations

import copy

import numpy as np

from magctl.core.batched import rows_times
from magctl.plant.coils import CoilActuator
from magctl.plant.drive import ActuatedRobot, Drive
from magctl.plant.fluid.lubrication import film_gap
from magctl.plant.fluid.wall_drag import accurate_coefficients
from magctl.plant.outline import Polygon
from magctl.plant.robot import StickSlipRobot, steady_speed
from magctl.plant.sphere import Spheres, separate_spheres
from magctl.plant.standin import (
    _STRAIGHT,
    FieldGait,
    KinematicRobot,
    StandinSpheres,
    StandinTracker,
    StraightToTarget,
)
from reference.core_blocks import NumpyForm, SteppedForm


def _numpy_form(block, cls):
    """``block`` (same parameters) as the reference class ``cls``: for a fused block's parts."""
    ref = copy.copy(block)
    ref.__class__ = cls
    return ref


def _norm(v: np.ndarray) -> np.ndarray:
    return np.sqrt(np.einsum("...i,...i->...", v, v))


# --- coils, drive, stick-slip robot ----------------------------------------------------------------------
class RefCoilActuator(SteppedForm, CoilActuator):
    """Allocation, limits (static currents scaled as a vector, the oscillation given what is left), RL step."""

    def _solve(self, state, u):
        i_s = self.allocation.static_currents(u["b_static"])
        ai = np.abs(i_s)
        s_static = None
        if (ai > self.coils.current_limit).any():
            # decided over the batch (the kernel decides per trial: they differ only within rounding of a limit)
            s_static = 1.0 / np.maximum((ai * self._inv_imax).max(axis=1), 1.0)
            i_s *= s_static[:, None]
            ai *= s_static[:, None]
        # oscillation: only the coils that carry it (|A⁺ row| > 0); s = min(1, cap / |b_osc|)
        freq = np.maximum(u["freq"], 0.0)
        az = ai[:, self._zc]
        w = freq[:, None] * self._two_pi_l
        z = np.sqrt(self._r2 + w * w)
        cap = np.minimum(self._imax_z - az, (self._vmax_z - self._r_z * az) / z)
        cap *= self._inv_pz
        cap_min = cap[:, 0]
        for c in range(1, cap.shape[1]):
            cap_min = np.minimum(cap_min, cap[:, c])
        s_osc = np.minimum(cap_min / np.maximum(np.abs(u["b_osc"]), 1e-300), 1.0)
        if self._vclip:
            i_s = np.clip(i_s, -self._vmax_over_r, self._vmax_over_r)
        i_avg = i_s + (state["i"] - i_s) * self.avg_weight
        sat = s_osc < 1.0 - 1e-12
        if s_static is not None:
            sat |= s_static < 1.0
        return i_s, i_avg, s_osc, freq, sat

    def step(self, state, u):
        i_s, i_avg, s_osc, freq, sat = self._solve(state, u)
        out = {"currents": i_avg, "b_static_delivered": rows_times(i_avg, self._A_xy),
               "b_osc_delivered": u["b_osc"] * s_osc, "freq_delivered": freq, "saturated": sat}
        return out, {"i": i_s + (state["i"] - i_s) * self.decay}



class RefDrive(NumpyForm, Drive):
    def output(self, state, u):
        s = self.settings
        sp = np.minimum(np.maximum(u["speed"], 0.0), s.max_speed)
        f = np.interp(sp, self._v_table, self._f_table)
        on = sp > 0.0
        f *= on
        psi = u["heading"]
        b_static = np.empty((psi.shape[0], 2))
        b_static[:, 0] = np.cos(psi)
        b_static[:, 1] = np.sin(psi)
        b_static *= s.static_field
        return {"b_static": b_static, "b_osc": on * s.osc_field, "freq": f}


class RefStickSlipRobot(NumpyForm, StickSlipRobot):
    """Heading by the exact solution, stick-slip speed (times the step variation), Simpson's rule."""

    def output(self, state, u):
        return {"position": state["pos"], "heading": state["psi"], "velocity": state["vel"], "tilt": state["tilt"]}

    def update(self, state, u):
        h = self.dt
        b = u["b_static_delivered"]
        bmag = np.hypot(b[:, 0], b[:, 1])
        psi_b = np.arctan2(b[:, 1], b[:, 0])
        # tan(e/2) is 2π-periodic in e, so e = ψ − ψ_B needs no wrapping
        t0 = np.tan(0.5 * (state["psi"] - psi_b))
        k = np.exp(self._half_rate * bmag)  # e^{−(h/2)/τ_ψ}
        tk = t0 * k
        psis = np.empty((bmag.shape[0], 3))
        psis[:, 0] = state["psi"]
        psis[:, 1] = psi_b + 2.0 * np.arctan(tk)
        psis[:, 2] = psi_b + 2.0 * np.arctan(tk * k)
        # θ_a = atan(b_osc/|B|) / √(1 + (ωτ_θ)²) with ωτ_θ = c f / |B|  (see _stickslip.rocking_amplitude)
        freq = np.maximum(u["freq_delivered"], 0.0)
        theta = np.arctan2(np.abs(u["b_osc_delivered"]), bmag) * bmag / np.maximum(
            np.hypot(bmag, self._pitch_c * freq), 1e-300)
        v = freq * np.maximum(self._cos0 - np.cos(theta), 0.0)
        v *= self._eta_l
        if self.cv > 0 and state["rng"] is not None:  # no stream: the mean step (a linearisation's path)
            v *= np.maximum(1.0 + self.cv * state["rng"].standard_normal(at=state["k"]), 0.0)
        # Simpson's rule over the frame for ∫ v e^{iψ} dt, weights 1, 4, 1
        vel = np.empty((v.shape[0], 2))
        vel[:, 0] = rows_times(np.cos(psis), self._simpson)
        vel[:, 1] = rows_times(np.sin(psis), self._simpson)
        vel *= v[:, None]
        psi1 = np.remainder(psis[:, 2] + np.pi, 2.0 * np.pi) - np.pi
        return {"pos": state["pos"] + vel * h, "psi": psi1, "vel": vel, "tilt": theta * (2.0 / np.pi),
                "rng": state["rng"], "k": state["k"] + 1}


class RefActuatedRobot(NumpyForm, ActuatedRobot):
    """The three references in a row: drive command, coil field and RL step, robot step."""

    def output(self, state, u):
        out = _numpy_form(self.robot, RefStickSlipRobot).output(state["robot"], u)
        out["saturated"] = state["saturated"]
        return out

    def update(self, state, u):
        co = _numpy_form(self.coils, RefCoilActuator)
        cmd = _numpy_form(self.drive, RefDrive).output(None, u)
        i_s, i_avg, s_osc, freq, sat = co._solve(state["coils"], cmd)
        delivered = {"b_static_delivered": rows_times(i_avg, co._A_xy), "b_osc_delivered": cmd["b_osc"] * s_osc,
                     "freq_delivered": freq}
        i_next = i_s + (state["coils"]["i"] - i_s) * co.decay
        robot = _numpy_form(self.robot, RefStickSlipRobot).update(state["robot"], delivered)
        return {"coils": {"i": i_next}, "robot": robot, "saturated": sat}


# --- spheres -----------------------------------------------------------------------------------------------
def push_out_of_outline(rel: np.ndarray, outline, radius: float, iterations: int = 3):
    """Move circle centres ``rel (..., 2)`` (robot frame) so circles of ``radius`` do not overlap ``outline``.

    ``outline`` is a ``(V, 2)`` polygon or a :class:`~magctl.plant.outline.Polygon`.
    Returns the corrected centres and a bool array of which ones were in contact.
    Several passes settle a sphere wedged in the concave front face.
    """
    rel = np.asarray(rel, float)
    x, y, touched = _push_out(rel[..., 0].ravel(), rel[..., 1].ravel(), outline, radius, iterations)
    if touched.any():
        rel = np.stack([x, y], axis=-1).reshape(rel.shape)
    return rel, touched.reshape(rel.shape[:-1])


def _push_out(x: np.ndarray, y: np.ndarray, outline, radius: float, iterations: int):
    """:func:`push_out_of_outline` on flat coordinate arrays; returns new ``x, y`` and ``touched``.

    A pass leaves centres it did not move as they were, so later passes only revisit the
    centres moved by the pass before.
    """
    poly = outline if isinstance(outline, Polygon) else Polygon(outline)
    touched = np.zeros(x.shape, bool)
    idx = None                                     # centres still being settled (None: all)
    for _ in range(iterations):
        px, py = (x, y) if idx is None else (x[idx], y[idx])
        dist, nx, ny = poly.distance(px, py)
        inside = poly.contains(px, py)
        hit = inside | (dist < radius * (1 - 1e-9))
        if not hit.any():
            break
        rows = np.nonzero(hit)[0] if idx is None else idx[hit]
        touched[rows] = True
        d = np.maximum(dist[hit], 1e-15)
        sign = np.where(inside[hit], -1.0, 1.0)
        nhx, nhy = nx[hit], ny[hit]
        ux, uy = (px[hit] - nhx) / d, (py[hit] - nhy) / d
        if idx is None:
            x, y = x.copy(), y.copy()
        x[rows] = nhx + (ux * sign) * radius
        y[rows] = nhy + (uy * sign) * radius
        idx = rows
    return x, y, touched


def _complex(xy: np.ndarray) -> np.ndarray:
    """Points ``(..., 2)`` as complex numbers ``x + iy`` (a fresh array)."""
    z = np.empty(xy.shape[:-1], complex)
    z.real, z.imag = xy[..., 0], xy[..., 1]
    return z


class RefSpheres(NumpyForm, Spheres):
    """One frame in numpy array operations over the batch: sub-steps of flow look-up, the move ``V_p = k U``
    (eq 4), the gap balance (eq 8-9), non-penetration of the footprint and between spheres."""

    def output(self, state, u):
        return {"spheres": state["xy"].copy(), "contact": state["contact"].copy()}

    def update(self, state, u):
        # Plane points and vectors are complex numbers x + iy inside the frame: a rotation by the
        # heading is then one multiplication by e^{±iθ} (fewer array operations per sub-step).
        pos = _complex(np.asarray(u["position"], float))
        heading = np.asarray(u["heading"], float)
        vel = _complex(np.asarray(u["velocity"], float))
        z = _complex(state["xy"])
        gap, mult = state["gap"].copy(), state["mobility"]
        n_sub = self.params.substeps
        tau = self.dt / n_sub
        contact = np.zeros(len(heading), bool)
        # the robot's heading and velocity are held over the frame: rotate once
        turn = (np.cos(heading) + 1j * np.sin(heading))[:, None]        # body → world
        back = turn.conj()                                               # world → body
        vb = vel[:, None] * back
        vbx, vby = vb.real, vb.imag
        k_rest = np.minimum(np.full(gap.shape, self._k_contact) * mult, 1.0)   # every sphere on the glass
        # robot positions at the middle and the end of every sub-step, (B, n_sub)
        steps = np.arange(n_sub, dtype=float)
        p_mid = pos[:, None] + vel[:, None] * (steps + 0.5) * tau
        p_end = pos[:, None] + vel[:, None] * (steps + 1) * tau
        for k in range(n_sub):
            k_now = self._capped(mult, gap) if (gap > 0).any() else k_rest
            rel = (z - p_mid[:, k, None]) * back                        # robot frame
            ux, uy, uz = self.flow.lookup_components(rel.real, rel.imag, vbx, vby)
            v = k_now * ((ux + 1j * uy) * turn)
            if self.film_cutoff > 0 or self.edge_cutoff > 0:
                v, closed = self._film(v, z, gap, mult, pos + vel * k * tau, vel, turn, tau)
                contact |= closed
            z += v * tau
            gap = np.maximum(gap + self._gap_rate(uz, gap) * tau, 0.0)
            z, touched = self._contacts(z, p_end[:, k], turn)
            contact |= touched
        return {"xy": np.stack([z.real, z.imag], axis=-1), "gap": gap, "mobility": mult, "contact": contact}

    def _film(self, v, z, gap, mult, p_start, vel, turn, tau):
        """Robot–sphere lubrication (magctl.plant.fluid.lubrication: face film or edge law per edge): each
        sphere's velocity along the outline's normal replaced by the one that advances the gap exactly over
        the sub-step."""
        v = v.copy()
        closed = np.zeros(len(z), bool)
        poly, r, mu = self._footprint, self.radius, self.flow.viscosity
        h_min, h_face, h_edge = self.contact_gap, self.film_cutoff, self.edge_cutoff
        rel = (z - p_start[:, None]) * turn.conj()
        near = np.abs(z - p_start[:, None]) < self.reach + max(h_face, h_edge)
        for b, i in zip(*np.nonzero(near), strict=True):
            x, y = rel[b, i].real, rel[b, i].imag
            t = np.clip(((x - poly.x0) * poly.dx + (y - poly.y0) * poly.dy) / poly.ab2, 0.0, 1.0)
            qx, qy = poly.x0 + t * poly.dx, poly.y0 + t * poly.dy
            e = int(np.argmin((x - qx) ** 2 + (y - qy) ** 2))
            dist = np.hypot(x - qx[e], y - qy[e])
            if poly.contains(np.array(x), np.array(y)) or dist <= 0:
                continue
            h = max(dist - r, h_min)
            area, log_coef = self.film_area[e], self.edge_law[e]
            if not ((area > 0 and h < h_face) or (log_coef > 0 and h < h_edge)):
                continue
            n = complex((x - qx[e]) / dist, (y - qy[e]) / dist) * turn[b, 0]
            f_t, f_r, t_t, t_r, _, _ = accurate_coefficients((gap[b, i] + self.roughness) / r)
            zeta = 6 * np.pi * mu * r * abs((f_t * t_r - f_r * t_t) / t_r) / mult[b, i]
            un, vn = (vel[b] * n.conjugate()).real, (v[b, i] * n.conjugate()).real
            h1 = film_gap(h, (vn - un) * tau, 6 * np.pi * mu * area / zeta, h_face,
                          6 * np.pi * mu * log_coef / zeta, h_edge, h_min)
            closed[b] |= bool(h1 <= h_min and vn < un)
            v[b, i] += (un + (h1 - h) / tau - vn) * n
        return v, closed

    def _contacts(self, z, pos, turn):
        """Non-penetration of the robot's footprint and between spheres after a sub-step.

        ``z`` sphere centres (B, N) and ``pos`` robot positions (B,) as complex numbers, ``turn``
        = e^{iθ} (B, 1). Only spheres within reach of the robot (per trial and sphere) are tested.
        """
        touched = np.zeros(len(z), bool)
        d = z - pos[:, None]
        near = np.abs(d) < self.reach
        if near.any():
            b, i = np.nonzero(near)
            rel = d[b, i] * turn[b, 0].conj()
            # beyond the footprint's bounding box grown by R a sphere can neither touch nor overlap it
            box = (np.abs(rel.real) < self._box[0]) & (np.abs(rel.imag) < self._box[1])
            if not box.all():
                b, i, rel = b[box], i[box], rel[box]
            rx2, ry2, hit = _push_out(rel.real, rel.imag, self._footprint, self.radius, 3)
            if hit.any():
                b, i = b[hit], i[hit]
                z = z.copy()
                z[b, i] = pos[b] + (rx2[hit] + 1j * ry2[hit]) * turn[b, 0]
                touched[b] = True
        if self.n > 1:
            z = _complex(separate_spheres(np.stack([z.real, z.imag], axis=-1), self.radius))
        return z, touched


# --- the kinematic stand-in ----------------------------------------------------------------------------------
class RefKinematicRobot(NumpyForm, KinematicRobot):
    def output(self, state, u):
        return {"position": state["x"], "heading": state["h"], "velocity": state["v"]}

    def update(self, state, u):
        speed, heading = u["speed"], u["heading"]
        v = speed[:, None] * np.stack([np.cos(heading), np.sin(heading)], axis=1)
        steer = u["steer"] if "steer" in u else speed > 0
        # new arrays: the outputs handed out this frame stay untouched
        return {"x": state["x"] + self.dt * v, "h": np.where(steer, heading, state["h"]), "v": v}


class RefFieldGait(NumpyForm, FieldGait):
    def output(self, state, u):
        bs = u["b_static_delivered"]
        b_xy = _norm(bs)
        on = b_xy > 0
        speed = np.where(on, steady_speed(self.robot, b_xy, u["b_osc_delivered"], u["freq_delivered"]), 0.0)
        return {"speed": speed, "heading": np.arctan2(bs[:, 1], bs[:, 0]), "steer": on}


class RefStraightToTarget(NumpyForm, StraightToTarget):
    def output(self, state, u):
        d = u["target"] - u["position"]
        cap = np.where(u["speed_cap"] > 0, np.minimum(u["speed_cap"], self.v_max), 0.0)
        return {"speed": np.minimum(cap, _norm(d) / self.dt), "heading": np.arctan2(d[:, 1], d[:, 0])}


class RefStandinSpheres(NumpyForm, StandinSpheres):
    """Side pass (eq 22), release ``D_p,r``, contact, sphere–sphere separation, over the batch at once."""

    def output(self, state, u):
        return {"spheres": state["s"], "contact": state["contact"], "releases": state["releases"],
                "last_release": state["last_release"]}

    def update(self, state, u):
        r0, r = state["r"], u["position"]
        draw = state["rng"].standard_normal((), at=state["k"]) if state["rng"] is not None else np.zeros(r.shape[0])
        s = state["s"]
        if s.shape[1] == 0:
            return {**state, "r": r.copy(), "k": state["k"] + 1}
        step = r - r0
        size = _norm(step)
        moving = size > 1e-12
        d = np.where(moving[:, None], step / np.where(moving, size, 1.0)[:, None], 0.0)
        straight = moving & (np.einsum("bi,bi->b", d, state["dir"]) > _STRAIGHT)
        passed = state["passed"] & straight[:, None]  # one displacement per straight pass
        dd = np.broadcast_to(d[:, None, :], s.shape)

        # 1. side pass, eq 22
        rel0 = s - r0[:, None, :]
        a0 = np.einsum("bni,bni->bn", rel0, dd)
        a1 = np.einsum("bni,bni->bn", s - r[:, None, :], dd)
        lat = np.abs(dd[..., 0] * rel0[..., 1] - dd[..., 1] * rel0[..., 0])
        cross = (straight[:, None] & ~passed & (a0 > 0) & (a1 <= 0) & (lat > self.contact_distance)
                 & (lat < self.side_range))
        amp = self.side_amplitude * (self.side_scale[:, None] if self.side_scale.ndim else self.side_scale)
        s = s + (cross * amp * np.exp(-self.side_rate * lat))[..., None] * dd
        passed = passed | cross

        # 2. release: the sphere follows a robot that moves away from it
        away = moving[:, None] & (np.einsum("bni,bni->bn", s - r[:, None, :], dd) < 0)
        release = state["attached"] & away
        amount = np.maximum(0.0, self.release_mean + self.release_std * draw)
        pending = np.where(release, amount[:, None], state["pending"])
        follow = np.where(away, np.minimum(pending, size[:, None]), 0.0)
        s = s + follow[..., None] * dd
        pending = pending - follow
        attached = state["attached"] & ~release
        started = release.any(axis=1)

        # 3. contact: carried along d in front of a moving robot, else pushed out along the line of centres
        c = self.contact_distance
        rel = s - r[:, None, :]
        along = np.einsum("bni,bni->bn", rel, dd)
        lat = np.abs(dd[..., 0] * rel[..., 1] - dd[..., 1] * rel[..., 0])
        reach = np.sqrt(np.maximum(c * c - lat * lat, 0.0))
        carried = moving[:, None] & (along > -1e-12) & (lat < c) & (along < reach * (1 - 1e-9))
        s = s + (carried * (reach - along))[..., None] * dd
        rel = s - r[:, None, :]
        dist = _norm(rel)
        over = dist < c * (1 - 1e-9)  # a rounding-level overlap (a carried or following sphere) is none
        s = np.where(over[..., None], r[:, None, :] + rel * (c / np.where(dist > 0, dist, 1.0))[..., None], s)
        over |= carried
        # a sphere left exactly at contact distance still touches (unless the robot is leaving it): whether
        # rounding puts it a hair inside or outside must not decide whether it is released later
        touching = over | ((dist < c * (1 + 1e-9)) & ~away)

        # 4. sphere-sphere: the sphere the robot did not drive gives way
        s = self._separate(s, over | (follow > 0))
        return {"s": s, "contact": over.any(axis=1), "r": r.copy(), "dir": np.where(moving[:, None], d, state["dir"]),
                "attached": attached | touching, "pending": np.where(touching, 0.0, pending), "passed": passed,
                "releases": state["releases"] + release.sum(axis=1),
                "last_release": np.where(started, amount, state["last_release"]), "rng": state["rng"],
                "k": state["k"] + 1}

    def _separate(self, s: np.ndarray, driven: np.ndarray) -> np.ndarray:
        n, gap = s.shape[1], 2.0 * self.sphere_radius
        if n < 2 or gap <= 0:
            return s
        s = s.copy()
        for i in range(n):
            for j in range(i + 1, n):
                sep = s[:, j] - s[:, i]
                dist = _norm(sep)
                fix = np.where(dist < gap, gap - dist, 0.0)
                if not fix.any():
                    continue
                v = sep / np.where(dist > 0, dist, 1.0)[:, None]
                move_j = ~driven[:, j]
                s[:, j] += np.where(move_j, fix, 0.0)[:, None] * v
                s[:, i] -= np.where(move_j, 0.0, fix)[:, None] * v
        return s


def _within(t: float, window) -> bool:
    return window is not None and window[0] <= t < window[1]


class RefStandinTracker(NumpyForm, StandinTracker):
    def output(self, state, u):
        return {"robot_est": state["r"], "heading_est": state["h"], "velocity_est": state["v"],
                "spheres_est": state["s"], "lost": state["lost"]}

    def update(self, state, u):
        p = u["position"]
        k = state["k"] + 1
        t = k * self.dt  # the time at which this estimate is shown
        lost = np.any(np.abs(p) > self.half_width, axis=1)
        if _within(t, self.blackout):
            lost = np.ones_like(lost)
        s = np.full_like(u["spheres"], np.nan) if _within(t, self.sphere_loss) else u["spheres"].copy()
        return {"r": p.copy(), "h": u["heading"].copy(), "v": (p - state["r"]) / self.dt, "s": s, "lost": lost,
                "k": k}


REFERENCES = {CoilActuator: RefCoilActuator, Drive: RefDrive, StickSlipRobot: RefStickSlipRobot,
              ActuatedRobot: RefActuatedRobot, Spheres: RefSpheres, KinematicRobot: RefKinematicRobot,
              FieldGait: RefFieldGait, StraightToTarget: RefStraightToTarget, StandinSpheres: RefStandinSpheres,
              StandinTracker: RefStandinTracker}
