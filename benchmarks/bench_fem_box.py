"""The paper's COMSOL box by finite elements (opt-in: ``python benchmarks/run.py --only fem_box``).

For each box size (L × W × H, W the half-width of the half model) and mesh size, solves the box
(:mod:`magctl.plant.fluid.fem_box`, cached on disk), then runs the Fig 6 side pass with the box's flow
in :class:`magctl.plant.sphere.Spheres` and reports: unknowns, mesh and solve times, peak memory,
D_s at D_g = 370 / 500 / 650 µm, the eq-22-form fit ``D_s = a exp(-b D_g)`` on the non-contact gaps
of 200–650 µm, the contact threshold, and the sphere's lateral drift just above the threshold
(positive: pushed away from the robot's path; negative: pulled in). The unbounded boundary-element
model is run alongside as the reference. Targets are the paper's numbers (eq 22: a = 1755 µm,
b = 0.009042 /µm; threshold ≈ 370 µm with pull-in); the question is which box reproduces them.

Needs the ``fem`` extra; takes ~10–20 minutes from a cold cache on a shared 2-core machine
(``quick``: one box, one coarse mesh).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from magctl.core.units import UM_PER_M

GAPS = np.linspace(200e-6, 650e-6, 24)
AT = np.array([370e-6, 500e-6, 650e-6])
PAPER = {"a_um": 1755.0, "b_per_um": 0.009042, "contact_threshold_um": 370.0, "drift": "pull-in",
         "D_s_um": [61.8, 19.1, 4.9]}
BOXES_MM = [(3.0, 1.5, 1.0), (3.0, 1.5, 0.5), (2.0, 1.0, 0.5)]
MESH_UM = [60.0, 40.0, 28.0]


def lateral_drift(gap: float, **block_kw) -> dict:
    """Side pass at ``gap``: the sphere's lateral offset [µm] when the robot is alongside and at the end."""
    from magctl.plant.fluid.scenarios import APPROACH, ROBOT_SPEED
    from magctl.plant.sphere import Spheres

    block = Spheres(np.array([[0.0, gap]]), **block_kw)
    state = block.initial_state(1)
    step = ROBOT_SPEED * block.dt
    xs = -APPROACH + step * np.arange(int(np.ceil(2 * APPROACH / step)))
    alongside = None
    for x in xs:
        state = block.update(state, {"position": np.array([[x, 0.0]]), "heading": np.zeros(1),
                                     "velocity": np.array([[ROBOT_SPEED, 0.0]])})
        if alongside is None and x >= state["xy"][0, 0, 0]:
            alongside = float(state["xy"][0, 0, 1] - gap)
    return {"gap_um": gap * UM_PER_M, "alongside_um": alongside * UM_PER_M,
            "final_um": float(state["xy"][0, 0, 1] - gap) * UM_PER_M}


def side_push(**block_kw) -> dict:
    """Fig 6 numbers for one flow: D_s at AT, the eq-22-form fit, the threshold and the drift above it."""
    from magctl.plant.fluid.scenarios import contact_threshold, sidepush_curve, sidepush_fit

    t0 = time.perf_counter()
    res = sidepush_curve(GAPS, **block_kw)
    free = ~res.contact
    a, b, r2 = sidepush_fit(GAPS[free], res.displacement[free])
    thr = contact_threshold(**block_kw)
    drift = lateral_drift(thr + 5e-6, **block_kw)
    return {"D_s_um": (np.interp(AT, GAPS, res.displacement) * UM_PER_M).tolist(), "a_um": a * UM_PER_M,
            "b_per_um": b / UM_PER_M, "r2": r2, "contact_threshold_um": thr * UM_PER_M,
            "drift_above_threshold": drift,
            "drift": "pushed out" if drift["final_um"] > 0 else "pull-in",
            "curve_um": {"gaps": (GAPS * UM_PER_M).tolist(), "D_s": (res.displacement * UM_PER_M).tolist(),
                         "along": (res.along * UM_PER_M).tolist(), "contact": res.contact.tolist()},
            "backward": bool(np.any(res.along[free] < 0)),
            "side_pass_time_s": time.perf_counter() - t0}


def one_box(box_mm, mesh_um: float, outlet: str = "velocity") -> dict:
    from magctl.plant.fluid.domain import Domain
    from magctl.plant.fluid.fem_box import BoxFlow

    length, half_width, depth = (v * 1e-3 for v in box_mm)
    t0 = time.perf_counter()
    flow = BoxFlow.build(domain=Domain("box", depth, length, half_width), mesh_size=mesh_um * 1e-6, outlet=outlet)
    out = {"box_mm": {"L": box_mm[0], "W_half": box_mm[1], "H": box_mm[2]}, "mesh_um": mesh_um, "outlet": outlet,
           "build_time_s": time.perf_counter() - t0, "fem": flow.info}
    out.update(side_push(flow=flow))
    print(json.dumps({k: out[k] for k in ("box_mm", "mesh_um", "outlet", "D_s_um", "a_um", "b_per_um",
                                          "contact_threshold_um", "drift")}, default=float), file=sys.stderr,
          flush=True)
    return out


def run(quick: bool = False, boxes=None, meshes=None, outlets=("velocity",)) -> dict:
    """Every (box, mesh) pair; ``outlets`` adds the traction-free rear face for the first box and the finest mesh."""
    from magctl.plant.fluid.fem_box import require_fem

    try:
        require_fem()
    except ImportError as exc:
        return {"skipped": str(exc)}
    boxes = boxes or (BOXES_MM[:1] if quick else BOXES_MM)
    meshes = meshes or ([60.0] if quick else MESH_UM)
    out = {"paper": PAPER, "unbounded": side_push(), "runs": []}
    for box in boxes:
        for m in meshes:
            out["runs"].append(one_box(box, m))
    for outlet in outlets:
        if outlet != "velocity":
            out["runs"].append(one_box(boxes[0], meshes[-1], outlet))
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "results_fem_box.json")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--box", nargs=3, type=float, action="append", metavar=("L", "W", "H"),
                        help="box in mm (W the half-width); repeat for several")
    parser.add_argument("--mesh", nargs="*", type=float, help="element sizes on the robot [µm]")
    parser.add_argument("--outlet", nargs="*", default=["velocity"], choices=["velocity", "traction"])
    args = parser.parse_args()
    res = run(args.quick, [tuple(b) for b in args.box] if args.box else None, args.mesh, tuple(args.outlet))
    args.out.write_text(json.dumps(res, indent=2, default=float))
    print(f"wrote {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
