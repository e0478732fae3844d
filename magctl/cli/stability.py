"""``magctl stability servo|front|side``: loop analyses under one command.

``servo`` is registered by :mod:`magctl.cli.stability_servo`; ``front`` and ``side``
here print the reports of :mod:`magctl.cli.stability_reports` (the analyses of :mod:`magctl.stability`).
"""

from __future__ import annotations

from magctl.cli.common import add_json, bounded_float, emit
from magctl.cli.stability_servo import register_servo

GAIN = bounded_float(-1e3, 1e3, "a learning gain")
DISTANCE_UM = bounded_float(0.0, 1e4, "a distance in µm on the slide")
OFFSET_UM = bounded_float(-1e4, 1e4, "a distance in µm on the slide")
SCALE = bounded_float(1e-3, 1e3, "a scale factor")


def register(sub) -> None:
    p = sub.add_parser("stability", help="stability analysis of the servo and push loops")
    inner = p.add_subparsers(dest="loop", metavar="LOOP")
    inner.required = True
    register_servo(inner)
    _register_front(inner)
    _register_side(inner)


def _register_front(subparsers) -> None:
    """Add ``front --kc K [--delta0-um D] [--json]`` to the ``magctl stability`` subparsers."""
    p = subparsers.add_parser("front", help="front-push learning loop (eq 13-15): poles, verdict, convergence")
    p.add_argument("--kc", type=GAIN, required=True, help="learning gain K_c of eq 13")
    p.add_argument("--delta0-um", type=OFFSET_UM, default=0.0, help="initial compensation δ(0) in µm (default 0)")
    p.add_argument("--model", choices=["paper", "identified"], default="paper",
                   help="release model: the paper's eq 14 0th-order plant, D_p,r ~ N(300, 75²) µm (paper), or the "
                        "release map identified from the closed loop, models/front_release.toml (identified)")
    add_json(p)
    p.set_defaults(func=cmd_front)


def _register_side(subparsers) -> None:
    """Add ``side --ks K [--model lin|exp] [--ratio R] [--plant-scale S] [--plant-gap-scale G] [--json]``."""
    p = subparsers.add_parser("side", help="side-push learning loop (eq 16-20, 22-23): poles, verdicts, ranges")
    p.add_argument("--ks", type=GAIN, required=True, help="learning gain K_s of eq 18")
    p.add_argument("--model", choices=["lin", "exp"], default="lin", help="controller model: eq 23 (lin) or 22 (exp)")
    p.add_argument("--ratio", type=SCALE, default=None,
                   help="model ratio rho of the linear analyses (default: the plant scale when the model is exp "
                        "and the plant eq 22 scaled, else 1)")
    p.add_argument("--min-gap-um", type=DISTANCE_UM, default=None,
                   help="minimum gap bound in µm (default: models/push.toml, 370 µm)")
    p.add_argument("--goal-um", type=DISTANCE_UM, default=None,
                   help="initial goal distance in µm (default: models/push.toml, 300 µm)")
    p.add_argument("--plant", choices=["exp", "fluid"], default="exp",
                   help="actual F_act: eq 22 (exp) or the fluid model's side-push curve (fluid, a few seconds)")
    p.add_argument("--plant-scale", type=SCALE, default=1.0,
                   help="multiply the plant's displacements (eq 22 scaled: a mismatched plant; default 1)")
    p.add_argument("--plant-gap-scale", type=SCALE, default=1.0,
                   help="stretch the plant's gap axis (a curve decaying this many times more slowly; default 1)")
    add_json(p)
    p.set_defaults(func=cmd_side)


def cmd_front(args) -> int:
    from magctl.cli.stability_reports import front_report

    doc = front_report(args.kc, args.delta0_um, model=args.model)
    emit(args, doc, _front_summary)
    return 0


def cmd_side(args) -> int:
    from magctl.cli.stability_reports import side_report

    doc = side_report(args.ks, args.model, min_gap_um=args.min_gap_um, goal_um=args.goal_um, ratio=args.ratio,
                      plant=args.plant, plant_scale=args.plant_scale, plant_gap_scale=args.plant_gap_scale)
    emit(args, doc, _side_summary)
    return 0


def _fmt_poles(poles: list) -> str:
    return ", ".join(f"{p['re']:.4g}{p['im']:+.4g}j" if p["im"] else f"{p['re']:.4g}" for p in poles)


def _front_summary(d: dict) -> str:
    lines = [
        f"front push, K_c = {d['kc']:g}, δ(0) = {d['delta0_um']:g} µm",
        f"  G_cl(z) = {d['kc']:g} / (z - 1 + {d['kc']:g});  pole(s): {_fmt_poles(d['poles'])}",
        f"  verdict: {d['verdict']} ({d['damping']});  stable for {d['stable_gain_range'][0]:g} < K_c < "
        f"{d['stable_gain_range'][1]:g}",
    ]
    c = d.get("convergence")
    if c and c["model"] == "identified":
        by = ", ".join(f"{x:.2f}" for x in c["p_converged_by_attempt"])
        lines.append(f"  release map identified from the closed loop (models/front_release.toml), ε_p "
                     f"{c['eps_p_um']:g} µm: mean attempts {c['mean_attempts']:.2f} (failures at "
                     f"{c['max_attempts']}); P(not converged) = {c['p_not_converged_monte_carlo']:.3g}; "
                     f"converged by attempt 1..{c['max_attempts']}: {by}")
    elif c:
        lines.append(f"  D_p,r ~ N({c['release_mean_um']:g} µm, ({c['release_std_um']:g} µm)²), "
                     f"ε_p {c['eps_p_um']:g} µm: "
                     f"P(not converged in {c['max_attempts']}) = {c['p_not_converged_markov']:.3g} (Markov), "
                     f"{c['p_not_converged_monte_carlo']:.3g} (Monte Carlo); mean attempts "
                     f"{c['mean_attempts_if_converged']:.2f}")
    return "\n".join(lines)


def _side_summary(d: dict) -> str:
    pa, ff, sw, op, nl = (d["paper_analysis"], d["with_feedforward"], d["switched"], d["operating_range"],
                          d["nonlinear_map"])
    rng = ff["stable_gain_range"]
    runs = ", ".join(f"[{a:g}, {b:g}]" for a, b in sw["stable_gain_ranges"]) or "none"
    ray = sw["growing_ray"]
    lines = [
        f"side push, K_s = {d['ks']:g}, model {d['model']}, plant {d['plant']}, min gap {d['min_gap_um']:g} µm",
        f"  ratio {d['ratio']:g} ({d['ratio_source']})",
        f"  verdict: {d['verdict']} ({d['verdict_source']})",
        f"  [eq 19-20 as printed] poles {_fmt_poles(pa['poles'])}: {pa['verdict']} ({pa['damping']}), "
        f"stable for {pa['stable_gain_range'][0]:g} < K_s < {pa['stable_gain_range'][1]:g}",
        f"  [signed 1-D model] poles {_fmt_poles(ff['poles'])}: {ff['verdict']} ({ff['damping']})"
        + (f", stable for {rng[0]:g} < K_s < {rng[1]:g}" if rng else ", no stable K_s"),
        f"  [switched, as the task runs] {sw['verdict']}: |e| grows x{sw['growth_rate']:.4g} per attempt "
        f"(attempt map: x{sw['growth_rate_attempt_map']:.4g}); stable K_s (0..4 by 0.02): {runs}",
        "    branch poles: " + "; ".join(f"{k} {_fmt_poles(v)}" for k, v in sw["branch_poles"].items())
        + "; JSR bounds (any switching) {:.3g}..{:.3g}".format(*sw["jsr_bounds_any_switching"]),
    ]
    if ray:
        lines.append(f"    a ray returns x{ray['multiplier_per_attempt']:.4g} per attempt after "
                     f"{' -> '.join(ray['branches'])}" + (" (repelling: other starts converge)"
                                                          if sw["verdict"] == "stable" else ""))
    lines += [
        f"  local model ratio over the operating range: {op['local_ratio_min']:.3g} .. {op['local_ratio_max']:.3g}",
        f"  nonlinear map from {d['goal_um']:g} µm: "
        + (f"converged in {nl['attempts']} attempts" if nl["converged"] else f"not converged in {nl['max_attempts']}")
        + (f"; converges from every start for K_s in [{nl['stable_gain_range'][0]:g}, {nl['stable_gain_range'][1]:g}]"
           if nl["stable_gain_range"] else ""),
    ]
    return "\n".join(lines)
