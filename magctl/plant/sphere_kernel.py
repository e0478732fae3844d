"""Compiled sphere sub-steps: one frame of :class:`magctl.plant.sphere.Spheres` for a whole batch.

The array form (``Spheres._update_arrays``) makes about 150 numpy calls per sub-step; at the
batch sizes of a study (≈ 100 trials) each call is dominated by its fixed cost, not
by the arithmetic. This module runs the same frame — flow look-up in the robot-frame
map, inertia-free move ``V_p = k U`` (eq 4), gap balance (eq 8–9; in the ``accurate`` mode
with Brenner's and Goren & O'Neill's wall factors, ``Spheres._gap_rate``), non-penetration of
the footprint and between spheres — as one numba-compiled loop over trials, spheres
and sub-steps, with the same operations in the same order per trial.

Off the flow map it sums the flow's far-field point forces (``RobotFlow.points/forces``)
as Blake Stokeslets — singular ones (``eps = 0``) for the boundary-element flow — as the
array form does. Both drag modes are compiled for a sphere at any gap: the ``paper`` mode's
eq 4–5, and the ``accurate`` mode's tabulated resistance functions
(:func:`wall_functions`: the spline of ``models/wall_resistance.toml`` passed in as the arrays of
:class:`magctl.plant.fluid.wall_drag.WallTable`, and the near-contact expansions, reflections and
blend of :mod:`magctl.plant.fluid.wall_drag`, whose shared definitions are compiled here unchanged).

numba's on-disk cache of this module is keyed on this file only: after editing the formulas it
compiles from ``wall_drag.py`` (``near_contact_terms``, ``far_field_terms``, ``smoothstep``,
``blend``), delete ``magctl/plant/__pycache__/sphere_kernel*.nb*`` (the kernel tests would
otherwise fail against the edited array form).
"""

from __future__ import annotations

import numba
import numpy as np

from magctl.plant.fluid.wall_drag import (
    ROT_BOUND,
    SHEAR_CONTACT,
    STAGNATION_CONTACT,
    blend,
    far_field_terms,
    near_contact_terms,
    smoothstep,
)

# a push-out pass counts a centre as touching below this fraction of R (the array form's tolerance)
_TOUCH = 1.0 - 1e-9


@numba.njit(cache=True, nogil=True)
def _stokeslet_flow(px, py, pz, vbx, vby, points, forces, eps, viscosity):
    """Flow at robot-frame ``(px, py, pz)`` summed over the flow's far-field (regularised) Blake Stokeslets
    (``magctl.plant.fluid.stokes.regularized_blake_velocity``, term by term), for body velocity
    ``(vbx, vby)`` as the combination of the two unit motions."""
    e2 = eps * eps
    u = np.zeros((2, 3))
    for m in range(points.shape[0]):
        h = points[m, 2]
        r = (px - points[m, 0], py - points[m, 1], pz - h)
        big = (r[0], r[1], pz + h)                       # from the image point (y1, y2, -h)
        r2 = r[0] * r[0] + r[1] * r[1] + r[2] * r[2]
        big2 = big[0] * big[0] + big[1] * big[1] + big[2] * big[2]
        d3 = (r2 + e2) ** 1.5
        ib = 1.0 / np.sqrt(big2)
        ib3 = ib * ib * ib
        ib5 = ib3 * ib * ib
        w_direct = (r2 + 2 * e2) / d3
        c_g = 2 * h * (h - big[2]) * ib3
        for k in range(2):
            f = (forces[k, m, 0], forces[k, m, 1], forces[k, m, 2])
            g = (f[0], f[1], -f[2])                      # the mirrored force
            rf = r[0] * f[0] + r[1] * f[1] + r[2] * f[2]
            rrf = big[0] * f[0] + big[1] * f[1] + big[2] * f[2]
            rrg = big[0] * g[0] + big[1] * g[1] + big[2] * g[2]
            w_r = rf / d3
            w_big = -rrf * ib3 + 6 * h * (big[2] - h) * ib5 * rrg - 2 * h * ib3 * g[2]
            for i in range(3):
                u[k, i] += w_direct * f[i] - ib * f[i] + c_g * g[i] + w_r * r[i] + w_big * big[i]
            u[k, 2] += 2 * h * ib3 * rrg
    scale = 8.0 * np.pi * viscosity
    return ((vbx * u[0, 0] + vby * u[1, 0]) / scale, (vbx * u[0, 1] + vby * u[1, 1]) / scale,
            (vbx * u[0, 2] + vby * u[1, 2]) / scale)


@numba.njit(cache=True, nogil=True)
def _flow_at(x, y, vbx, vby, flat, gx, gy, dgx, dgy, points, forces, eps, viscosity, height):
    """Flow ``(u_x, u_y, u_z)`` at robot-frame ``(x, y)`` for body velocity ``(vbx, vby)``: bilinear
    in the map, summed directly beyond it (``RobotFlow.lookup_components``)."""
    nx, ny = gx.shape[0], gy.shape[0]
    if abs(x) > gx[nx - 1] or abs(y) > gy[ny - 1]:
        return _stokeslet_flow(x, y, height, vbx, vby, points, forces, eps, viscosity)
    ix = min(max(np.searchsorted(gx, x) - 1, 0), nx - 2)
    iy = min(max(np.searchsorted(gy, y) - 1, 0), ny - 2)
    tx = (x - gx[ix]) / dgx[ix]
    ty = (y - gy[iy]) / dgy[iy]
    sx, sy = 1 - tx, 1 - ty
    w00, w01, w10, w11 = sx * sy, tx * sy, sx * ty, tx * ty
    c = iy * nx + ix
    out = np.empty(6)
    for j in range(6):
        out[j] = w00 * flat[c, j] + w01 * flat[c + 1, j] + w10 * flat[c + nx, j] + w11 * flat[c + nx + 1, j]
    return out[0] * vbx + out[3] * vby, out[1] * vbx + out[4] * vby, out[2] * vbx + out[5] * vby


@numba.njit(cache=True, nogil=True)
def _paper_mobility(radius, gap, roughness):
    """V_p/U of eq 4 with eq 5 (``magctl.plant.fluid.wall_drag.paper_mobility``) at one gap."""
    h = radius + gap + roughness
    lg = np.log((gap + roughness) / radius)
    f_shear = 1.0 + 0.7005 * radius / h
    f_trans = min(8.0 / 15.0 * lg - 0.9588, -1.0)
    f_rot = max(-2.0 / 15.0 * lg - 0.2526, 0.0)
    q = radius / h
    w = -2.375e-6 * np.exp(12.05 * q) + 1.025 * np.exp(-0.1438 * q)
    rot = min(max(w, 0.0), ROT_BOUND)
    return -f_shear / (f_trans + rot * f_rot)


@numba.njit(cache=True, nogil=True)
def wall_functions(d, table, out):
    """The accurate mode's eight functions ``(f_t, f_r, t_t, t_r, f_s, t_s, λ, g)`` at one δ/a = ``d``
    into ``out (8,)``, with the steps of ``magctl.plant.fluid.wall_drag._evaluate`` for one gap:
    the cubic spline of ln|f| in ln δ/a (evaluated as scipy's ``PPoly``: interval by bisection,
    ``c3 + c2 s + c1 s² + c0 s³`` summed in that order), blended below the table with the
    near-contact expansions (Chaoui & Feuillebois 2003; Cox & Brenner 1967) and above it with the
    reflections (Faxén; Goldman, Cox & Brenner 1967a,b; Lorentz).

    ``table`` is a :class:`~magctl.plant.fluid.wall_drag.WallTable` (a tuple of its fields).
    """
    knots, coef, signs, near_lo, near_hi, far_lo, far_hi = table
    lx = np.log(d)
    x = min(max(lx, near_lo), far_hi)
    n = knots.shape[0]
    i = min(max(np.searchsorted(knots, x, side="right") - 1, 0), n - 2)
    s = x - knots[i]
    s2 = s * s
    s3 = s2 * s
    for j in range(8):
        c = coef[j, i]
        v = 0.0 + c[3]
        v = v + c[2] * s
        v = v + c[1] * s2
        v = v + c[0] * s3
        out[j] = signs[j] * np.exp(v)
    if lx < near_hi:
        w = 1.0 - smoothstep(lx, near_lo, near_hi)
        f_t, f_r, t_t, t_r, lam = near_contact_terms(d)
        out[0] = blend(w, f_t, out[0])
        out[1] = blend(w, f_r, out[1])
        out[2] = blend(w, t_t, out[2])
        out[3] = blend(w, t_r, out[3])
        out[4] = blend(w, SHEAR_CONTACT[0], out[4])
        out[5] = blend(w, SHEAR_CONTACT[1], out[5])
        out[6] = blend(w, lam, out[6])
        out[7] = blend(w, STAGNATION_CONTACT, out[7])
    if lx > far_lo:
        w = smoothstep(lx, far_lo, far_hi)
        far = far_field_terms(d)
        for j in range(8):
            out[j] = blend(w, far[j], out[j])


@numba.njit(cache=True, nogil=True)
def accurate_state(radius, gap, roughness, table, out):
    """V_p/U, λ and g of a sphere at gap δ in the ``accurate`` mode, at δ/a = (δ + ε)/R
    (``wall_drag.accurate_mobility`` and ``wall_drag.normal_factors``: the free-sphere force and
    torque balance of Goldman, Cox & Brenner 1967b; Brenner's 1961 normal drag factor; Goren &
    O'Neill's 1971 wall-flow factor). ``out (8,)`` is scratch for :func:`wall_functions`."""
    wall_functions((gap + roughness) / radius, table, out)
    f_t, f_r, t_t, t_r, f_s, t_s = out[0], out[1], out[2], out[3], out[4], out[5]
    half = 0.5 * radius / (radius + gap + roughness)
    det = f_t * t_r - f_r * t_t
    return (-f_s * t_r + f_r * half * t_s) / det, out[6], out[7]


@numba.njit(cache=True, nogil=True)
def _push_out_point(px, py, x0, y0, dx, dy, ab2, y1, radius, iterations):
    """One circle centre (robot frame) moved off the polygon: up to ``iterations`` passes of
    nearest-edge projection, as ``magctl.plant.sphere._push_out``. Returns ``x, y, touched``."""
    touched = False
    for _ in range(iterations):
        best, bx, by = np.inf, 0.0, 0.0
        crossings = 0
        for e in range(x0.shape[0]):
            t = min(max(((px - x0[e]) * dx[e] + (py - y0[e]) * dy[e]) / ab2[e], 0.0), 1.0)
            qx, qy = x0[e] + t * dx[e], y0[e] + t * dy[e]
            ex, ey = px - qx, py - qy
            d2 = ex * ex + ey * ey
            if d2 < best:
                best, bx, by = d2, qx, qy
            if (y0[e] > py) != (y1[e] > py) and px < x0[e] + (py - y0[e]) * dx[e] / dy[e]:
                crossings += 1
        dist = np.sqrt(best)
        inside = crossings % 2 == 1
        if not (inside or dist < radius * _TOUCH):
            break
        touched = True
        d = max(dist, 1e-15)
        sign = -1.0 if inside else 1.0
        px = bx + ((px - bx) / d * sign) * radius
        py = by + ((py - by) / d * sign) * radius
    return px, py, touched


@numba.njit(cache=True, nogil=True)
def _separate(z, radius, iterations):
    """Overlapping spheres of one trial ``z (N,)`` pushed apart half each (``separate_spheres``)."""
    n = z.shape[0]
    npair = n * (n - 1) // 2
    cx = np.empty(npair)
    cy = np.empty(npair)
    for _ in range(iterations):
        any_overlap = False
        k = 0
        for i in range(n):
            for j in range(i + 1, n):
                ddx, ddy = z[j].real - z[i].real, z[j].imag - z[i].imag
                dist = np.sqrt(ddx * ddx + ddy * ddy)
                overlap = 2 * radius - dist
                if dist > 1e-12:
                    ux, uy = ddx / dist, ddy / dist
                else:   # no usable centre line: part them along x
                    ux, uy = 1.0, 0.0
                if overlap > 0:
                    any_overlap = True
                    cx[k], cy[k] = 0.5 * overlap * ux, 0.5 * overlap * uy
                else:
                    cx[k], cy[k] = 0.0, 0.0
                k += 1
        if not any_overlap:
            break
        k = 0
        for i in range(n):
            for j in range(i + 1, n):
                z[i] = complex(z[i].real - cx[k], z[i].imag - cy[k])
                z[j] = complex(z[j].real + cx[k], z[j].imag + cy[k])
                k += 1


@numba.njit(cache=True, nogil=True)
def sphere_frame(z, gap, mult, pos, vel, turn, n_sub, tau, flat, gx, gy, dgx, dgy, points, forces, eps,
                 viscosity, height,
                 x0, y0, dx, dy, ab2, y1, radius, reach, box_x, box_y, sink_rate, held_rate, adhesion_range,
                 k_contact, paper_mode, roughness, inv_lambda_contact, flow_push_contact, table):
    """Advance every trial's spheres by one frame of ``n_sub`` sub-steps, in place.

    Parameters
    ----------
    z : complex (B, N)
        Sphere centres ``x + iy`` [m]; overwritten.
    gap : float (B, N)
        Gaps δ [m]; overwritten.
    mult : float (B, N)
        Per-sphere mobility multiplier (sticky patches, release scatter).
    pos, vel, turn : complex (B,)
        Robot position, velocity (held over the frame) and ``e^{iθ}`` of its heading.
    flat, gx, gy, dgx, dgy
        The flow maps as one ``(ny·nx, 6)`` table and the grid (``RobotFlow._flat_maps``).
    points, forces, eps, viscosity, height
        The flow's far-field point forces (``RobotFlow``), for spheres off the map.
    x0, y0, dx, dy, ab2, y1
        Footprint edges (:class:`~magctl.plant.fluid.geometry.Polygon`).
    sink_rate, held_rate : float
        ``W_b/ζ`` and ``(W_b + P)/ζ`` of eq 8–9 [m/s]; the adhesion ``P`` acts within
        ``adhesion_range`` of the glass.
    k_contact, paper_mode, roughness
        V_p/U on the glass, whether the drag mode is ``paper`` (eq 4–5), and ε [m].
    inv_lambda_contact, flow_push_contact : float
        1/λ and g of the gap balance on the glass in the ``accurate`` mode (Brenner's normal drag
        factor and Goren & O'Neill's wall-flow factor at δ = 0, ``Spheres._gap_rate``); unused in
        the ``paper`` mode (eq 9 as printed).
    table : WallTable
        The ``accurate`` mode's resistance functions (:func:`wall_functions`), for lifted spheres;
        unused in the ``paper`` mode.

    Returns
    -------
    contact : bool (B,)
        Some sphere touched the robot during the frame.
    """
    batch, n = z.shape
    contact = np.zeros(batch, np.bool_)
    zb = np.empty(n, np.complex128)
    gb = np.empty(n)
    scratch = np.empty(8)
    for b in range(batch):
        back = turn[b].conjugate()
        vb = vel[b] * back
        for i in range(n):
            zb[i] = z[b, i]
            gb[i] = gap[b, i]
        touched = False
        for k in range(n_sub):
            p_mid = pos[b] + vel[b] * (k + 0.5) * tau
            p_end = pos[b] + vel[b] * (k + 1.0) * tau
            for i in range(n):
                rel = (zb[i] - p_mid) * back
                ux, uy, uz = _flow_at(rel.real, rel.imag, vb.real, vb.imag, flat, gx, gy, dgx, dgy,
                                      points, forces, eps, viscosity, height)
                settle = held_rate if gb[i] <= adhesion_range else sink_rate
                # mobility (eq 4) and gap rate (eq 8-9) at the gap the sub-step starts from
                if paper_mode:
                    k_now = k_contact if gb[i] <= 0 else _paper_mobility(radius, gb[i], roughness)
                    rate = uz - settle
                elif gb[i] <= 0:    # accurate mode on the glass: (g U_z − settling) / λ at δ = 0
                    k_now = k_contact
                    rate = (flow_push_contact * uz - settle) * inv_lambda_contact
                else:               # accurate mode, lifted: the tabulated functions at (δ + ε)/R
                    k_now, lam, push = accurate_state(radius, gb[i], roughness, table, scratch)
                    rate = (push * uz - settle) * (1.0 / lam)
                # capped at the free-sphere limit 1
                zb[i] += min(k_now * mult[b, i], 1.0) * (complex(ux, uy) * turn[b]) * tau
                gb[i] = max(gb[i] + rate * tau, 0.0)
            for i in range(n):
                d = zb[i] - p_end
                if abs(d) >= reach:
                    continue
                rel = d * back
                if not (abs(rel.real) < box_x and abs(rel.imag) < box_y):
                    continue
                rx, ry, hit = _push_out_point(rel.real, rel.imag, x0, y0, dx, dy, ab2, y1, radius, 3)
                if hit:
                    zb[i] = p_end + complex(rx, ry) * turn[b]
                    touched = True
            if n > 1:
                _separate(zb, radius, 3)
        for i in range(n):
            z[b, i] = zb[i]
            gap[b, i] = gb[i]
        contact[b] = touched
    return contact
