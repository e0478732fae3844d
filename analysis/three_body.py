"""The three-body check: the robot, a sphere in front of its notch and the glass in one Stokes problem.

The plant moves a sphere by the robot-only flow at its centre (eq 4) and, within a radius of the robot's
face, by the lubrication between them (docs/fluid.md §5). This study solves the problem those pieces
approximate (:mod:`magctl.plant.fluid.three_body`) for the robot translating towards a sphere on its axis,
at a ladder of gaps to the notch, and sets the free sphere's speed beside the plant's two predictions:
one-way (the flow alone) and with the film.

* **Wall gap.** The boundary elements resolve the sphere–glass gap at ``SOLVED_GAP`` = 0.1 a; the
  measured 25 nm is reached by adding the lone sphere's exact wall resistances (Stokesian dynamics'
  lubrication splitting, :func:`~magctl.plant.fluid.three_body.at_wall_gap`). The splitting is checked
  inside the resolved range: carried from 0.2 a to 0.1 a it is compared with the direct solve there.
* **Convergence.** One gap solved on three meshes (``MESH_SCALES``).
* **The law near contact.** For each gap, the resistance the plant needs to give the three-body speed,
  read as a face film's area ``A`` in ``6πμA/h`` and fitted over all gaps by the edge law
  ``6πμaC ln(h_e/h)`` (:func:`~magctl.plant.fluid.lubrication.fit_edge_law`): the fit is where
  ``models/sphere.toml [contact]`` takes ``edge_law`` and ``edge_law_cutoff`` from.

Not part of ``magctl reproduce`` (a dozen boundary-element solves of 5 000–12 000 panels, ~15 min).
"""

from __future__ import annotations

import numpy as np

from magctl.core.units import UM
from magctl.plant.fluid.geometry import RobotGeometry
from magctl.plant.fluid.lubrication import fit_edge_law
from magctl.plant.fluid.params import fluid_viscosity, sphere_params
from magctl.plant.fluid.three_body import (
    Mesh,
    at_wall_gap,
    glide_resistance,
    needed_resistance,
    notch_front,
    predict,
    robot_only_flow,
    solve_response,
)
from magctl.plant.fluid.wall_drag import accurate_mobility
from magctl.studies.runner import Computed, PaperRow, StudyContext

NAME = "three-body"
TITLE = "Robot, sphere and glass in one Stokes problem — the check of the plant's one-way flow and film"
ORDER = 34
REPRODUCE = False  # about a dozen boundary-element solves: run it by name

GAPS = (0.5, 0.2, 0.1, 0.05, 0.02)
"""Gaps between the sphere and the notch's footprint edge, in sphere radii."""
SOLVED_GAP = 0.1
"""Sphere–glass gap the boundary elements resolve, in radii."""
CHECK_GAP = 0.05
"""The robot gap (radii) of the convergence table and of the wall-gap splitting check."""
MESH_SCALES = (1.4, 1.0, 0.85)


def _case(geometry, radius, viscosity, gap, wall_gap, scale=1.0):
    centre = np.array([notch_front(geometry) + radius * (1.0 + gap), 0.0, radius * (1.0 + wall_gap)])
    return solve_response(geometry, centre, radius, viscosity, Mesh().scaled(scale))


def compute(ctx: StudyContext) -> Computed:
    geometry = RobotGeometry.from_params()
    contact = sphere_params()
    radius, eps = contact.radius, contact.roughness
    cutoff = contact.film_cutoff * radius
    viscosity = fluid_viscosity()
    rows = []
    for gap in ctx.progress(GAPS, "three-body gaps"):
        resp = _case(geometry, radius, viscosity, gap, SOLVED_GAP)
        at_eps = at_wall_gap(resp, geometry, radius, viscosity, eps)
        solved = predict(geometry, resp.centre, radius, resp.flow[0], contact)
        lowered = resp.centre.copy()
        lowered[2] = radius + eps
        u_eps = float(robot_only_flow(geometry, viscosity, lowered[None])[0, 0])
        model = predict(geometry, lowered, radius, u_eps, contact)
        needed = needed_resistance(float(at_eps[0]), model.one_way, glide_resistance(eps / radius))
        h = model.gap_footprint / radius
        rows.append({"gap_a": gap, "gap_footprint_um": model.gap_footprint / UM, "gap_3d_um": resp.gap_robot / UM,
                     "panels": resp.panels,
                     "solved": {"three_body": float(resp.velocity[0]), "one_way": solved.one_way,
                                "face_film": solved.face_film, "film": solved.with_film},
                     "at_eps": {"three_body": float(at_eps[0]), "one_way": model.one_way,
                                "face_film": model.face_film, "film": model.with_film},
                     "needed": needed, "film_area_a2": needed / (1.0 / h - radius / cutoff)})
    conv = []
    for scale in MESH_SCALES:
        resp = _case(geometry, radius, viscosity, CHECK_GAP, SOLVED_GAP, scale)
        conv.append({"scale": scale, "panels": resp.panels, "velocity_x": float(resp.velocity[0]),
                     "velocity_z": float(resp.velocity[1]), "spin": float(resp.velocity[2])})
    high = _case(geometry, radius, viscosity, CHECK_GAP, 2 * SOLVED_GAP)
    direct = next(c for c in conv if c["scale"] == 1.0)["velocity_x"]
    carried = float(at_wall_gap(high, geometry, radius, viscosity, SOLVED_GAP * radius)[0])
    c_fit, h_fit, residual = fit_edge_law([r["gap_footprint_um"] * UM / radius for r in rows],
                                          [r["needed"] for r in rows])
    results = {"radius_um": radius / UM, "roughness_nm": eps / 1e-9, "solved_wall_gap_a": SOLVED_GAP,
               "film_cutoff_a": cutoff / radius, "rows": rows, "convergence": conv,
               "splitting_check": {"from_gap_a": 2 * SOLVED_GAP, "to_gap_a": SOLVED_GAP, "direct": direct,
                                   "carried": carried, "relative_error": carried / direct - 1.0},
               "edge_law": {"coefficient": c_fit, "cutoff_a": h_fit, "largest_residual": residual,
                            "used_coefficient": contact.edge_coefficient, "used_cutoff_a": contact.edge_cutoff},
               "lone_mobility_at_eps": float(accurate_mobility(radius, 0.0, eps))}
    return Computed(results)


def draw(computed: Computed, ctx: StudyContext) -> list:
    from magctl.studies.figures import pyplot, save_figure

    plt = pyplot()
    rows = computed.results["rows"]
    h = [r["gap_footprint_um"] for r in rows]
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for key, style, label in (("three_body", "o-", "robot + sphere + glass (BEM)"),
                              ("one_way", "s--", "plant, one-way flow (eq 4)"),
                              ("face_film", "^:", "face film 6πμA/h"),
                              ("film", "v-.", "plant: edge law 6πμaC ln(h_e/h)")):
        ax.plot(h, [r["at_eps"][key] for r in rows], style, label=label)
    ax.set_xscale("log")
    ax.set_xlabel("gap between sphere and notch edge, footprint (µm)")
    ax.set_ylabel("sphere speed / robot speed")
    ax.set_title(f"Sphere on the robot's axis, wall gap {computed.results['roughness_nm']:.0f} nm", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return [save_figure(fig, ctx.figure_path("three_body"), dpi=120)]


def summarise(computed: Computed) -> tuple[list[str], list[PaperRow]]:
    r = computed.results
    lines = [f"Sphere of radius {r['radius_um']:.0f} µm on the robot's axis, robot moving towards it; solved at a "
             f"wall gap of {r['solved_wall_gap_a']:g} a, carried to {r['roughness_nm']:.0f} nm by the lone sphere's "
             "exact wall resistances.", "",
             "| gap (footprint, µm) | 3-D gap (µm) | panels | BEM | one-way | face film | edge law | "
             "R needed (6πμa) | as A/a² (1/h) |", "|---|---|---|---|---|---|---|---|---|"]
    for row in r["rows"]:
        e = row["at_eps"]
        lines.append(f"| {row['gap_footprint_um']:.3f} | {row['gap_3d_um']:.1f} | {row['panels']} | "
                     f"{e['three_body']:.3f} | {e['one_way']:.3f} | {e['face_film']:.3f} | {e['film']:.3f} | "
                     f"{row['needed']:.5g} | {row['film_area_a2']:.2f} |")
    fit = r["edge_law"]
    lines += ["", f"Edge law fitted to the resistance needed: C = {fit['coefficient']:.4g}, h_e = "
              f"{fit['cutoff_a']:.4g} a (largest residual {fit['largest_residual']:.1%}); the plant uses "
              f"C = {fit['used_coefficient']:g}, h_e = {fit['used_cutoff_a']:g} a (models/sphere.toml)."]
    lines += ["", "Mesh convergence (robot gap 0.05 a, wall gap 0.1 a):", "",
              "| mesh scale | panels | V_x | V_z | aΩ_y |", "|---|---|---|---|---|"]
    lines += [f"| {c['scale']:g} | {c['panels']} | {c['velocity_x']:.4f} | {c['velocity_z']:.4f} | {c['spin']:.4f} |"
              for c in r["convergence"]]
    s = r["splitting_check"]
    lines += ["", f"Wall-gap splitting carried from {s['from_gap_a']:g} a to {s['to_gap_a']:g} a: "
              f"V_x {s['carried']:.4f} against {s['direct']:.4f} solved directly ({s['relative_error']:+.1%})."]
    return lines, []
