"""Fig 6 by domain: which bounds of the oil give the paper's side-push curve (paper §IV-C, §IV-D).

The paper fitted eq 22 (D_s = 1755 µm · exp(−0.009042/µm · D_g), R² = 0.997) to its COMSOL
simulation, and saw the sphere pulled in below a 370 µm gap. Unbounded oil (filling
the half-space above the glass) decays more slowly and pushes the sphere out. The COMSOL model
was a finite box — inlet and outlet faces, a moving ground, symmetry faces, a half model — and a
real rig holds a finite layer of oil. This study draws D_s(D_g) for each domain of
:class:`magctl.plant.fluid.domain.Domain` with the same robot, sphere and drag:

* the unbounded half-space (Blake's images);
* a layer of depth H under a no-slip lid and with a free surface, H = 0.5, 1, 2 mm
  (boundary elements, :mod:`magctl.plant.fluid.flow`);
* with ``--fem``, the paper's COMSOL box at three sizes (finite elements,
  :mod:`magctl.plant.fluid.fem_box`; minutes, needs the ``fem`` extra).

For each: the eq-22-form fit (a, b) on the non-contact gaps, D_s at 370 / 500 / 650 µm (signed:
negative where the sphere ends up behind its start, carried back by the oil returning round the
robot in a thin layer), the contact threshold, and the sphere's sideways drift just outside it
(pull-in or push-out). Not part of ``magctl reproduce`` (minutes of flow solves on a cold cache).
"""

from __future__ import annotations

import numpy as np

from magctl.core.units import UM, UM_PER_M
from magctl.plant.fluid.calibration import eq22, paper_side
from magctl.plant.fluid.domain import Domain
from magctl.plant.fluid.flow import robot_flow
from magctl.plant.fluid.scenarios import contact_threshold, sidepush_curve, sidepush_fit
from magctl.studies.runner import Computed, PaperRow, StudyContext

NAME = "fig6-domain"
TITLE = "Fig 6 by domain — which bounds of the oil give the paper's side-push curve"
ORDER = 32
REPRODUCE = False  # seven boundary-element solves (10–40 s each on a cold cache): run it by name

PAPER_THRESHOLD_UM = 370.0  # paper §IV-D
GAPS = np.linspace(200e-6, 650e-6, 24)
AT = np.array([370e-6, 500e-6, 650e-6])
LAYERS = (Domain(), *(Domain(kind, h) for kind in ("lid", "free_surface") for h in (0.5e-3, 1e-3, 2e-3)),
          Domain("lid", 1.05e-3))   # the default domain (models/fluid.toml), fitted to Fig 6
BOXES = (Domain("box", 1e-3, 4e-3, 2e-3), Domain("box", 1e-3, 3e-3, 1.5e-3), Domain("box", 2e-3, 3e-3, 1.5e-3))
FEM_MESH = 28e-6  # robot-surface element size of the box runs; D_s within 1 % of 20 µm (docs/fluid.md §3b)


def flow_for(domain: Domain):
    """The robot's flow in ``domain``: boundary elements for layers, finite elements for the box."""
    if domain.kind == "box":
        from magctl.plant.fluid.fem_box import BoxFlow

        return BoxFlow.build(domain=domain, mesh_size=FEM_MESH)
    return robot_flow(domain=domain)


def domain_curve(domain: Domain) -> dict:
    """D_s(D_g), its fit, the contact threshold and the drift just outside it, for one domain (µm)."""
    flow = flow_for(domain)
    res = sidepush_curve(GAPS, flow=flow)
    threshold = contact_threshold(flow=flow)
    free = ~res.contact
    a, b, r2 = sidepush_fit(GAPS[free], res.displacement[free])
    at = sidepush_curve(AT, flow=flow)
    near = sidepush_curve([threshold + 10e-6], flow=flow)
    return {
        "domain": domain.label(), "kind": domain.kind, "depth_mm": domain.depth * 1e3 if domain.bounded else None,
        "gaps_um": (GAPS * UM_PER_M).tolist(), "displacement_um": (res.displacement * UM_PER_M).tolist(),
        "contact": res.contact.tolist(),
        "fit": {"a_um": a * UM_PER_M, "b_per_um": b / UM_PER_M, "r2": r2},
        "at_um": {f"{g * UM_PER_M:.0f}": float(np.copysign(d, al) * UM_PER_M)
                  for g, d, al in zip(AT, at.displacement, at.along, strict=True)},
        "contact_threshold_um": threshold * UM_PER_M,
        # sideways drift of a sphere 10 µm outside the threshold: negative = pulled towards the robot's line
        "drift_near_threshold_um": float(near.across[0] * UM_PER_M),
    }


def verdict(curves: list[dict]) -> dict:
    """The domain closest to the paper in decay rate b and contact threshold (equal weight, relative)."""
    def score(c):
        return (abs(c["fit"]["b_per_um"] / (paper_side()["rate"] / UM_PER_M) - 1.0)
                + abs(c["contact_threshold_um"] / PAPER_THRESHOLD_UM - 1.0))

    best = min(curves, key=score)
    unbounded = next(c for c in curves if c["kind"] == "unbounded")
    return {"best": best["domain"], "best_b_per_um": best["fit"]["b_per_um"],
            "best_threshold_um": best["contact_threshold_um"], "best_drift_um": best["drift_near_threshold_um"],
            "b_error": best["fit"]["b_per_um"] / (paper_side()["rate"] / UM_PER_M) - 1.0,
            "unbounded_b_per_um": unbounded["fit"]["b_per_um"],
            "unbounded_threshold_um": unbounded["contact_threshold_um"]}


def compute(ctx: StudyContext) -> Computed:
    """Every layer domain, and the box domains with ``--fem``."""
    domains = list(LAYERS) + (list(BOXES) if ctx.fem else [])
    curves = [domain_curve(d) for d in ctx.progress(domains, "domains", total=len(domains))]
    eq22_printed = paper_side()
    paper = {"a_um": eq22_printed["amplitude"] / UM, "b_per_um": eq22_printed["rate"] / UM_PER_M,
             "contact_threshold_um": PAPER_THRESHOLD_UM,
             "at_um": {f"{g * UM_PER_M:.0f}": float(d * UM_PER_M) for g, d in zip(AT, eq22(AT), strict=True)}}
    results = {"domains": curves, "paper": paper, "verdict": verdict(curves), "fem": bool(ctx.fem)}
    return Computed(results, {"curves": curves})


def draw(computed: Computed, ctx: StudyContext) -> list:
    """D_s(D_g) per domain on a log axis beside eq 22, and the decay rate b against depth."""
    from magctl.studies.figures import pyplot, save_figure

    plt = pyplot()
    curves = computed.data["curves"]
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4.2))
    g = np.linspace(200, 650, 100)
    ax.semilogy(g, eq22(g / UM_PER_M) * UM_PER_M, "k-", lw=2.5, label="paper eq 22 (COMSOL)")
    styles = {"unbounded": ("C0", "-"), "lid": ("C1", "--"), "free_surface": ("C2", "-."), "box": ("C3", ":")}
    for c in curves:
        col, ls = styles[c["kind"]]
        d = np.asarray(c["displacement_um"])
        ok = d > 0
        width = 1.0 + (c["depth_mm"] or 0.0)
        ax.semilogy(np.asarray(c["gaps_um"])[ok], d[ok], color=col, ls=ls, lw=width, label=c["domain"])
    ax.axvline(PAPER_THRESHOLD_UM, color="k", lw=0.8, alpha=0.5)
    ax.set_xlabel("side gap D_g (µm)")
    ax.set_ylabel("sphere displacement D_s (µm)")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3, which="both")
    for kind, (col, _) in styles.items():
        pts = [(c["depth_mm"], c["fit"]["b_per_um"]) for c in curves if c["kind"] == kind and c["depth_mm"]]
        if pts:
            h, b = np.array(sorted(pts)).T
            bx.plot(h, b, "o-", color=col, label=kind.replace("_", " "))
    unb = next(c for c in curves if c["kind"] == "unbounded")
    bx.axhline(unb["fit"]["b_per_um"], color="C0", label="unbounded")
    bx.axhline(paper_side()["rate"] / UM_PER_M, color="k", lw=2.5, label="paper eq 22")
    bx.set_xlabel("oil depth H (mm)")
    bx.set_ylabel("decay rate b (1/µm)")
    bx.legend(fontsize=8)
    bx.grid(alpha=0.3)
    return [save_figure(fig, ctx.figure_path("fig6_domain"), dpi=120)]


def summarise(computed: Computed) -> tuple[list[str], list[PaperRow]]:
    """One line per domain and the verdict."""
    r = computed.results
    v = r["verdict"]
    lines = []
    for c in r["domains"]:
        at = c["at_um"]
        drift = "pull-in" if c["drift_near_threshold_um"] < 0 else "push-out"
        lines.append(f"- {c['domain']}: a = {c['fit']['a_um']:.0f} µm, b = {c['fit']['b_per_um']:.5f} /µm; "
                     f"D_s(370/500/650) = {at['370']:.1f} / {at['500']:.1f} / {at['650']:.1f} µm; "
                     f"threshold {c['contact_threshold_um']:.0f} µm "
                     f"({drift} {abs(c['drift_near_threshold_um']):.0f} µm)")
    p = r["paper"]["at_um"]
    lines.append(f"- paper eq 22: b = {paper_side()['rate'] / UM_PER_M:.6f} /µm; D_s(370/500/650) = {p['370']:.1f} / "
                 f"{p['500']:.1f} / {p['650']:.1f} µm; threshold ≈ 370 µm (pull-in)")
    lines.append(f"- closest to the paper: {v['best']} (b {v['b_error']:+.0%} from eq 22, threshold "
                 f"{v['best_threshold_um']:.0f} µm); the unbounded model predicts "
                 f"b = {v['unbounded_b_per_um']:.5f} /µm "
                 f"and a {v['unbounded_threshold_um']:.0f} µm threshold"
                 + ("" if r["fem"] else " (the COMSOL box itself runs with --fem)"))
    paper_b = paper_side()["rate"] / UM_PER_M
    paper = [PaperRow("Fig 6 decay rate b", f"{paper_b:.6f} /µm", f"{v['best_b_per_um']:.5f} /µm",
                      f"closest domain: {v['best']}; unbounded {v['unbounded_b_per_um']:.5f} /µm")]
    return lines, paper
