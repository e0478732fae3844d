"""``magctl fluid``: the fluid model's inverse-model numbers (side-push gap, D_p,r, pull-off)."""

from __future__ import annotations

from magctl.cli.common import add_json, emit, positive_float
from magctl.core.errors import MagctlError


class FluidInputError(MagctlError):
    """A fluid command got an impossible argument."""


def register(sub) -> None:
    p = sub.add_parser("fluid", help="fluid model: side-push curve, release displacement, pull-off force")
    fs = p.add_subparsers(dest="fluid_command", metavar="WHAT")
    fs.required = True

    s = fs.add_parser("sidepush", help="sphere displacement D_s for side gaps D_g (Fig 6) and the eq 22 fit")
    s.add_argument("--gap-um", type=positive_float, nargs="+", default=None,
                   help="side gaps D_g in µm (default 200-650)")
    s.add_argument("--ds-um", type=positive_float, default=None,
                   help="also give the gap D_g for this desired D_s in µm (eq 22)")
    s.add_argument("--drag", choices=["paper", "accurate"], default=None,
                   help="near-wall drag: the exact resistance ('accurate', models/sphere.toml's default) or eq 4-5 as "
                        "printed ('paper')")
    s.add_argument("--roughness-nm", type=positive_float, default=None, help="sphere-glass roughness ε (default 25 nm)")
    add_json(s)
    s.set_defaults(func=cmd_sidepush)

    r = fs.add_parser("release", help="release displacement D_p,r after a front push")
    r.add_argument("--drag", choices=["paper", "accurate"], default=None,
                   help="near-wall drag: the exact resistance ('accurate', models/sphere.toml's default) or eq 4-5 as "
                        "printed ('paper')")
    r.add_argument("--roughness-nm", type=positive_float, default=None, help="sphere-glass roughness ε (default 25 nm)")
    add_json(r)
    r.set_defaults(func=cmd_release)

    q = fs.add_parser("pulloff", help="JKR pull-off range of a polystyrene sphere on glass under oil (eq 1-3)")
    q.add_argument("--radius-um", type=positive_float, default=105.0, help="sphere radius in µm (default 105)")
    add_json(q)
    q.set_defaults(func=cmd_pulloff)


def _roughness(args):
    if args.roughness_nm is None:
        return {}
    if args.roughness_nm <= 0:
        raise FluidInputError(f"--roughness-nm must be positive, got {args.roughness_nm}")
    return {"roughness": args.roughness_nm * 1e-9}


def cmd_sidepush(args) -> int:
    import numpy as np

    from magctl.plant.fluid.scenarios import gap_for_displacement, sidepush_curve, sidepush_fit

    gaps = np.linspace(200e-6, 650e-6, 24) if args.gap_um is None else np.asarray(args.gap_um) * 1e-6
    if np.any(gaps <= 0):
        raise FluidInputError("--gap-um values must be positive")
    res = sidepush_curve(gaps, drag_mode=args.drag, **_roughness(args))
    free = ~res.contact
    doc = {"points": [{"gap_um": g * 1e6, "displacement_um": d * 1e6, "contact": bool(c)}
                      for g, d, c in zip(gaps, res.displacement, res.contact, strict=True)]}
    if free.sum() >= 2:
        a, b, r2 = sidepush_fit(gaps[free], res.displacement[free])
        doc["fit"] = {"a_um": a * 1e6, "b_per_um": b * 1e-6, "r2": r2}
        if args.ds_um is not None:
            if args.ds_um <= 0:
                raise FluidInputError(f"--ds-um must be positive, got {args.ds_um}")
            doc["gap_for_ds_um"] = float(gap_for_displacement(args.ds_um * 1e-6, a, b)) * 1e6

    def text(d):
        lines = [f"D_g {p['gap_um']:6.1f} µm -> D_s {p['displacement_um']:7.1f} µm"
                 + ("  (contact)" if p["contact"] else "") for p in d["points"]]
        if "fit" in d:
            f = d["fit"]
            lines.append(f"fit: D_s = {f['a_um']:.0f} µm · exp(-{f['b_per_um']:.5f}/µm · D_g), R² = {f['r2']:.4f}")
        if "gap_for_ds_um" in d:
            lines.append(f"gap for D_s = {args.ds_um:g} µm: {d['gap_for_ds_um']:.1f} µm")
        return "\n".join(lines)

    emit(args, doc, text)
    return 0


def cmd_release(args) -> int:
    from magctl.plant.fluid.scenarios import release_displacement

    d = float(release_displacement(drag_mode=args.drag, **_roughness(args))[0])
    emit(args, {"release_displacement_um": d * 1e6}, lambda r: f"D_p,r = {r['release_displacement_um']:.1f} µm")
    return 0


def cmd_pulloff(args) -> int:
    from magctl.plant.fluid.surface import pull_off_range

    if args.radius_um <= 0:
        raise FluidInputError(f"--radius-um must be positive, got {args.radius_um}")
    r = pull_off_range(args.radius_um * 1e-6)
    doc = {"radius_um": args.radius_um, "pull_off_min_uN": r.p_min * 1e6, "pull_off_max_uN": r.p_max * 1e6,
           "work_of_adhesion_min_mJ_m2": r.w132_min * 1e3, "work_of_adhesion_max_mJ_m2": r.w132_max * 1e3}
    emit(args, doc, lambda d: f"{d['pull_off_min_uN']:.2f} µN < P < {d['pull_off_max_uN']:.2f} µN")
    return 0
