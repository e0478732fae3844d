"""The pass map: every sphere's displacement for a straight robot pass, identified from the plant.

The assembly planner (:mod:`magctl.control.assembly_planner`) predicts how one pass moves every sphere
on the slide, the ones already placed included. Its model is the cumulative form of Fig 6 that
:func:`magctl.plant.fluid.scenarios.pass_profile` measures on the sphere block of the closed loop: a sphere
at side gap ``h`` from the robot's line, the robot driving past from 3 mm before to 3 mm after it; the
sphere's displacement along the motion and away from the line after every frame, as a function of the
robot's position ``x`` relative to the sphere. A pass from ``x0`` to ``x1`` moves it by
``S(x1, h) − S(x0, h)`` (superposition along the path: the sphere's own ≤ 70 µm motion hardly changes the
flow it sees beyond the contact threshold; :func:`superposition_error` measures what it misses).

Below the contact threshold the robot would touch the sphere once it comes within ``min_gap``; the
planner never lets it (its passes keep ``min_gap`` from every sphere), so there the map is held at its
value where the robot's distance falls to ``min_gap``: the interpolating spline then does not carry contact
into the free region.

:func:`write_model` writes ``models/pass_map.toml``; a test regenerates it and compares.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from magctl.core.units import UM

REACH_UM = 3000.0
"""The map spans robot positions ±3 mm about the sphere: beyond, a pass moves it under 0.1 µm more."""
POSITION_STEP_UM = 100.0
GAPS_UM = (0, 100, 200, 300, 370, 430, 490, 550, 610, 670, 730, 790, 850, 910, 970, 1050, 1150, 1300,
           1500, 1750, 2000, 2500, 3000)
"""Side gaps of the map (µm): dense where the displacement changes fast, out to where it is ~0.1 µm."""


def identify(gaps_um=GAPS_UM, reach_um: float = REACH_UM, step_um: float = POSITION_STEP_UM,
             min_gap_um: float | None = None) -> dict:
    """Run the robot past spheres at ``gaps_um`` and tabulate ``S(x, h)`` every ``step_um`` (µm out).

    Returns ``positions_um`` (X,), ``gaps_um`` (G,), ``along_um`` and ``away_um`` (X, G), ``min_gap_um``
    and ``contact`` (G,), the gaps at which the full pass touches the sphere.
    """
    from magctl.config import load_model
    from magctl.plant.fluid.scenarios import pass_profile

    min_gap_um = float(load_model("push").side.min_gap) / UM if min_gap_um is None else float(min_gap_um)
    gaps = np.asarray(gaps_um, float)
    prof = pass_profile(gaps * UM, reach=reach_um * UM)
    grid = np.arange(-reach_um, reach_um + step_um / 2, step_um)
    x_um = prof.positions / UM
    along = np.stack([np.interp(grid, x_um, prof.along[:, j] / UM) for j in range(gaps.size)], axis=1)
    away = np.stack([np.interp(grid, x_um, prof.away[:, j] / UM) for j in range(gaps.size)], axis=1)
    for j, h in enumerate(gaps):
        if h < min_gap_um:  # hold the map where the robot comes within min_gap: the planner never goes nearer
            x_c = -np.sqrt(min_gap_um ** 2 - h ** 2)
            k = np.searchsorted(grid, x_c, side="right") - 1
            along[k + 1:, j], away[k + 1:, j] = along[k, j], away[k, j]
    return {"positions_um": grid, "gaps_um": gaps, "along_um": along, "away_um": away,
            "min_gap_um": min_gap_um, "contact": prof.contact}


def superposition_error(gaps_um=(370, 490, 610, 850, 1300), span_um=(-1000.0, 1000.0)) -> dict:
    """The map's prediction of one pass against the pass itself (:func:`sidepush_curve`), µm."""
    from magctl.plant.fluid.scenarios import sidepush_curve

    m = identify()
    g = np.asarray(gaps_um, float)
    x0, x1 = span_um
    pred = {}
    for key in ("along_um", "away_um"):
        ends = [np.interp([x0, x1], m["positions_um"], _column(m, key, h)) for h in g]
        pred[key] = np.array([e[1] - e[0] for e in ends])
    direct = sidepush_curve(g * UM, travel=(x1 - x0) / 2 * UM)
    return {"gaps_um": g, "predicted_along_um": pred["along_um"], "pass_along_um": direct.along / UM,
            "predicted_away_um": pred["away_um"], "pass_away_um": direct.across / UM}


def _column(m: dict, key: str, h: float) -> np.ndarray:
    """``S(·, h)`` on the map's positions, linear between its gaps."""
    j = int(np.clip(np.searchsorted(m["gaps_um"], h) - 1, 0, len(m["gaps_um"]) - 2))
    w = (h - m["gaps_um"][j]) / (m["gaps_um"][j + 1] - m["gaps_um"][j])
    return (1 - w) * m[key][:, j] + w * m[key][:, j + 1]


def model_toml(m: dict) -> str:
    """``models/pass_map.toml`` for the identified map ``m`` (µm, 4 decimals)."""
    def row(a):
        return "[" + ", ".join(f"{v:.4f}" for v in np.asarray(a, float).ravel()) + "]"

    src = ("magctl.studies.pass_map.identify(): magctl.plant.fluid.scenarios.pass_profile on the closed loop's "
           "sphere block (uncalibrated sphere, unbounded oil, robot at 0.4 mm/s)")
    lines = [
        "# The pass map: a sphere's displacement while the robot passes it on a straight line, as a function of",
        "# the robot's position x along its line relative to the sphere and the side gap h (docs/push-control.md §8).",
        "# Generated by magctl.studies.pass_map.write_model(); do not edit by hand:",
        "# tests/studies/test_pass_map.py regenerates it and compares.",
        "# along / away: displacement since x = -3 mm along the robot's motion / away from its line, rows = positions,",
        "# columns = gaps (row-major). Below min_gap the map is held where the robot's distance falls to min_gap.",
        "",
        "[provenance]",
        f'identified = {{ value = "pass_profile", source = "{src}" }}',
        f'min_gap_um = {{ value = {m["min_gap_um"]:.1f}, source = "models/push.toml side.min_gap_um at identification" }}',
        "",
        "[map]",
        f'positions_um = {{ value = {row(m["positions_um"])}, source = "robot position along its line minus the '
        f'sphere\'s, every {POSITION_STEP_UM:.0f} µm" }}',
        f'gaps_um = {{ value = {row(m["gaps_um"])}, source = "side gap from the robot\'s line to the sphere centre" }}',
        f'along_um = {{ value = {row(m["along_um"])}, source = "{src}" }}',
        f'away_um = {{ value = {row(m["away_um"])}, source = "{src}" }}',
        "",
    ]
    return "\n".join(lines)


def write_model(path: str | Path | None = None) -> Path:
    """Identify the map and write ``models/pass_map.toml`` (or ``path``)."""
    from magctl.config import models_dir

    path = Path(path) if path is not None else models_dir() / "pass_map.toml"
    path.write_text(model_toml(identify()))
    return path
