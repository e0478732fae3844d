"""Fig 6: sphere displacement D_s versus side gap D_g as the robot passes by (paper §IV-D).

The robot drives at 0.4 mm/s from 1 mm before to 1 mm past a sphere at side gap D_g
(robot centre line to sphere centre). The contact threshold is found from the
simulation (bisection on the gap at which the passing robot first touches the
sphere), the non-contact points are fitted with eq 22's form, and eq 22/23 are
drawn beside them, with the plant's error against eq 22 at 370-650 µm (the
one sphere every study uses: ε = 25 nm, the robot–sphere lubrication, the oil layer of
``models/fluid.toml``; no fitted sphere parameter).
"""

from __future__ import annotations

import numpy as np

from magctl.core.units import UM, UM_PER_M
from magctl.plant.fluid.calibration import FIG6_GAPS, eq22, eq23_gap, paper_side
from magctl.plant.fluid.domain import Domain
from magctl.plant.fluid.flow import robot_flow
from magctl.plant.fluid.params import sphere_params
from magctl.plant.fluid.scenarios import contact_threshold, sidepush_curve, sidepush_fit
from magctl.studies.runner import Computed, PaperRow, StudyContext

NAME = "sidepush-curve"
TITLE = "Fig 6 — side-push displacement D_s versus side gap D_g"
ORDER = 30

PAPER_THRESHOLD = 370e-6   # paper §IV-D
PAPER_R2 = 0.9971          # paper §VI-B
FLOW_SPEED = 0.4e-3  # robot speed of the flow map figure, m/s


def compute(ctx: StudyContext) -> Computed:
    """D_s(D_g), the contact threshold, eq 22-form fits, the error against eq 22, and the flow map."""
    gaps = np.linspace(200e-6, 650e-6, 24)
    res = sidepush_curve(gaps)
    threshold = contact_threshold()
    free = ~res.contact
    a, b, r2 = sidepush_fit(gaps[free], res.displacement[free])
    # eq 4-5 exactly as printed (the paper's own sphere model) beside the exact near-wall drag
    paper_drag = sidepush_curve(gaps, drag_mode="paper")
    pd_fit = sidepush_fit(gaps[~paper_drag.contact], paper_drag.displacement[~paper_drag.contact])
    judged = sidepush_curve(FIG6_GAPS)
    error = judged.displacement / eq22(FIG6_GAPS) - 1.0
    results = {
        "points": [{"gap_um": gg * UM_PER_M, "displacement_um": d * UM_PER_M, "along_um": al * UM_PER_M,
                    "contact": bool(c)}
                   for gg, d, al, c in zip(gaps, res.displacement, res.along, res.contact, strict=True)],
        "fit": {"a_um": a * UM_PER_M, "b_per_um": b / UM_PER_M, "r2": r2},
        "contact_threshold_um": threshold * UM_PER_M,
        "domain": Domain.from_params().label(),
        "drag_mode": sphere_params().drag_mode,
        "paper_drag_fit": {"a_um": pd_fit[0] * UM_PER_M, "b_per_um": pd_fit[1] / UM_PER_M, "r2": pd_fit[2]},
        "paper": {"a_um": paper_side()["amplitude"] / UM, "b_per_um": paper_side()["rate"] / UM_PER_M, "r2": PAPER_R2,
                  "contact_threshold_um": PAPER_THRESHOLD * UM_PER_M},
        "against_eq22": {"gaps_um": (FIG6_GAPS * UM_PER_M).tolist(),
                         "displacement_um": (judged.displacement * UM_PER_M).tolist(),
                         "eq22_um": (eq22(FIG6_GAPS) * UM_PER_M).tolist(), "error": error.tolist(),
                         "max_abs_error": float(np.abs(error).max())},
    }
    at = np.array([370e-6, 500e-6, 650e-6])
    data = {"gaps_m": gaps, "displacement_m": res.displacement, "contact": res.contact, "fit_m": (a, b, r2),
            "threshold_m": threshold,
            "at_m": at, "at_displacement_m": np.interp(at, gaps, res.displacement), "flow": flow_map(FLOW_SPEED)}
    return Computed(results, data)


def flow_map(speed: float) -> dict:
    """The robot's flow at the sphere-centre height on a 181 × 181 grid, ±900 µm (cf. the paper's Fig 5a).

    Returns ``x``, ``y`` (m), ``u`` (flow, m/s, ``(…, 3)``), ``ratio`` (|u_xy| / speed, NaN inside the
    robot), ``footprint`` (m, closed polygon) and ``height`` (m).
    """
    flow = robot_flow()
    x = np.linspace(-900e-6, 900e-6, 181)
    xx, yy = np.meshgrid(x, x)
    xy = np.stack([xx, yy], -1)
    u = flow.lookup(xy, np.broadcast_to([speed, 0.0], xy.shape))      # robot moving forward (+x)
    mag = np.linalg.norm(u[..., :2], axis=-1) / speed
    mag[flow.geometry.contains(np.concatenate([xy, np.full(xx.shape + (1,), flow.height)], -1))] = np.nan
    foot = np.vstack([flow.geometry.footprint, flow.geometry.footprint[:1]])
    return {"x": xx, "y": yy, "u": u, "ratio": mag, "footprint": foot, "height": flow.height, "speed": speed}


def draw(computed: Computed, ctx: StudyContext) -> list:
    """Fig 6 (D_s vs D_g with eq 22/23) and the flow map."""
    from magctl.studies.figures import pyplot, save_figure

    plt = pyplot()
    d = computed.data
    gaps, disp, free = d["gaps_m"], d["displacement_m"], ~d["contact"]
    a, b, r2 = d["fit_m"]
    fig, ax = plt.subplots(figsize=(7, 4.5))
    ax.semilogy(gaps[free] * UM_PER_M, disp[free] * UM_PER_M, "o", color="C0", label="magctl (ε = 25 nm)")
    ax.semilogy(gaps[~free] * UM_PER_M, disp[~free] * UM_PER_M, "x", color="C0", label="magctl, contact")
    g = np.linspace(200e-6, 650e-6, 200)
    ax.semilogy(g * UM_PER_M, a * np.exp(-b * g) * UM_PER_M, "-", color="C0", lw=1, label=f"magctl fit (R²={r2:.4f})")
    ax.semilogy(g * UM_PER_M, eq22(g) * UM_PER_M, "k--", label="paper eq 22 (Sim Fit)")
    ds = np.linspace(1e-6, 79e-6, 100)   # eq 23 over D_g = 200-620 µm
    ax.semilogy(eq23_gap(ds) * UM_PER_M, ds * UM_PER_M, "k:", label="paper eq 23 (Sim Fit Lin)")
    ax.axvline(d["threshold_m"] * UM_PER_M, color="C0", lw=0.8)
    ax.axvline(PAPER_THRESHOLD * UM_PER_M, color="k", lw=0.8, ls="--")
    ax.set_xlabel("D_g: side gap, robot centre line to sphere centre (µm)")
    ax.set_ylabel("D_s: sphere displacement (µm)")
    ax.set_title("Fig 6: side-push (vertical lines: contact threshold, magctl solid, paper dashed)", fontsize=9)
    ax.legend(fontsize=7)
    ax.grid(True, which="both", alpha=0.3)
    path = save_figure(fig, ctx.figure_path("sidepush_curve"), dpi=120)
    return [path, _flow_figure(d["flow"], ctx)]


def _flow_figure(flow: dict, ctx: StudyContext):
    """Top view of the robot's flow at the sphere-centre height (cf. the paper's Fig 5a)."""
    from magctl.studies.figures import pyplot, save_figure

    plt = pyplot()
    xx, yy, u, speed = flow["x"], flow["y"], flow["u"], flow["speed"]
    fig, ax = plt.subplots(figsize=(6, 5))
    cs = ax.contourf(xx * UM_PER_M, yy * UM_PER_M, flow["ratio"], levels=np.linspace(0, 1, 21), cmap="viridis")
    k = slice(None, None, 12)
    ax.quiver(xx[k, k] * UM_PER_M, yy[k, k] * UM_PER_M, u[k, k, 0], u[k, k, 1], color="w", scale=speed * 12)
    foot = flow["footprint"]
    ax.plot(foot[:, 0] * UM_PER_M, foot[:, 1] * UM_PER_M, "r-", lw=1)
    fig.colorbar(cs, ax=ax, label="|u| / robot speed")
    ax.set_aspect("equal")
    ax.set_xlabel("x (µm), robot moving towards +x (concave face at +x)")
    ax.set_ylabel("y (µm)")
    ax.set_title(f"Flow at the sphere-centre height z = {flow['height'] * UM_PER_M:.0f} µm\n"
                 "(red: footprint; white: solid at this height)", fontsize=9)
    return save_figure(fig, ctx.figure_path("flow_map"), dpi=120)


def summarise(computed: Computed) -> tuple[list[str], list[PaperRow]]:
    """Threshold, fit and D_s at three gaps against eq 22, and the largest error over 370-650 µm."""
    d, r = computed.data, computed.results
    a, b, r2 = d["fit_m"]
    threshold, at, ours = d["threshold_m"], d["at_m"], d["at_displacement_m"]
    judged = r["against_eq22"]
    summary = [
        f"- contact threshold: {threshold * UM_PER_M:.0f} µm (paper 370 µm)",
        f"- fit D_s = {a * UM_PER_M:.0f} µm · exp(-{b / UM_PER_M:.5f}/µm · D_g), R² = {r2:.4f} "
        f"(paper eq 22: 1755 µm · exp(-0.009042/µm · D_g), R² = 0.9971)",
        "- D_s at D_g = 370 / 500 / 650 µm: " + " / ".join(f"{v * UM_PER_M:.1f}" for v in ours)
        + " µm (eq 22: " + " / ".join(f"{v * UM_PER_M:.1f}" for v in eq22(at)) + " µm)",
        f"- against eq 22 at D_g = {judged['gaps_um'][0]:.0f}–{judged['gaps_um'][-1]:.0f} µm: errors "
        + ", ".join(f"{e:+.0%}" for e in judged["error"]) + f" (largest {judged['max_abs_error']:.0%})",
        f"- oil: {r['domain']}; near-wall drag {r['drag_mode']} (eq 4–5 as printed give a = "
        f"{r['paper_drag_fit']['a_um']:.0f} µm, b = {r['paper_drag_fit']['b_per_um']:.5f} /µm); "
        "the other domains: magctl study fig6-domain",
    ]
    paper = [
        PaperRow("side-push contact threshold D_g", "≈ 370 µm (sim)", f"{threshold * UM_PER_M:.0f} µm",
                 "sphere overlaps the robot footprint during the pass"),
        PaperRow("eq 22 a", "1755 µm", f"{a * UM_PER_M:.0f} µm", "exponential fit of non-contact points"),
        PaperRow("eq 22 b", "0.009042 /µm", f"{b / UM_PER_M:.5f} /µm",
                 f"{r['domain']} (unbounded oil decays more slowly: fig6-domain)"),
        PaperRow("D_s at D_g = 500 µm", f"{eq22(500e-6) * UM_PER_M:.1f} µm (eq 22)", f"{ours[1] * UM_PER_M:.1f} µm",
                 f"ε = 25 nm, {r['domain']}; largest error 370–650 µm {judged['max_abs_error']:.0%}"),
    ]
    return summary, paper
