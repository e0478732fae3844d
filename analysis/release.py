"""D_p,r: how far the sphere follows the robot as it backs away after a front push (paper §IV-D).

The sphere starts against the robot's concave front face; the robot retreats
1.5 mm at 0.4 mm/s. Uncalibrated (ε = 25 nm, paper drag and accurate drag) and
calibrated results are shown side by side, and a seeded Monte Carlo with the
block's variability (mobility scatter, sticky patches) shows the spread.
"""

from __future__ import annotations

import dataclasses

from magctl.plant.fluid.calibration import PAPER_RELEASE_EXPERIMENT, PAPER_RELEASE_SIMULATION, calibrate
from magctl.plant.fluid.params import sphere_params
from magctl.plant.fluid.scenarios import release_displacement
from magctl.studies.runner import Computed, PaperRow, StudyContext

NAME = "release"
TITLE = "Release displacement D_p,r after a front push"
ORDER = 31
DEFAULT_TRIALS = 200


UM = 1e6  # m → µm


def compute(ctx: StudyContext) -> Computed:
    """D_p,r uncalibrated (paper and accurate drag) and calibrated, the release paths, and a seeded Monte Carlo."""
    d0, retreat, path0 = release_displacement(return_path=True)
    d_acc = release_displacement(drag_mode="accurate")[0]
    cal = calibrate()
    cases = {"uncalibrated (ε = 25 nm)": (d0[0], path0[:, 0])}
    for k in ("release", "joint"):
        d, _, p = release_displacement(roughness=cal[k], return_path=True)
        cases[f"calibrated ε = {cal[k] * UM:.2f} µm ({k})"] = (d[0], p[:, 0])
    # Monte Carlo spread at the D_p,r-matched calibration
    n = ctx.n_trials(DEFAULT_TRIALS)
    varied = dataclasses.replace(sphere_params(), release_scatter=0.2, sticky_probability=0.1)
    mc = release_displacement(batch=n, seed=ctx.seed, roughness=cal["release"], params=varied)
    results = {
        "release_displacement_um": d0[0] * UM,
        "release_displacement_accurate_drag_um": d_acc * UM,
        "calibrated": {k: {"roughness_um": cal[k] * UM,
                           "release_displacement_um": release_displacement(roughness=cal[k])[0] * UM}
                       for k in ("release", "joint")},
        "monte_carlo": {"trials": n, "mean_um": float(mc.mean() * UM), "std_um": float(mc.std() * UM)},
        "paper": {"simulation_um": PAPER_RELEASE_SIMULATION * UM, "experiment_um": PAPER_RELEASE_EXPERIMENT * UM,
                  "experiment_spread_um": 75.0},
    }
    return Computed(results, {"retreat_m": retreat, "cases": cases, "monte_carlo_m": mc, "seed": ctx.seed})


def draw(computed: Computed, ctx: StudyContext) -> list:
    """Sphere displacement along the retreat for each case, and the Monte Carlo histogram."""
    from magctl.studies.figures import pyplot, save_figure

    plt = pyplot()
    d = computed.data
    retreat, mc, n = d["retreat_m"], d["monte_carlo_m"], computed.results["monte_carlo"]["trials"]
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(10, 4))
    for (label, (disp, p)), col in zip(d["cases"].items(), ("C0", "C3", "C2"), strict=True):
        ax.plot(retreat * UM, p * UM, color=col, label=f"{label}: {disp * UM:.0f} µm")
    ax.axhspan(225, 375, color="k", alpha=0.1, label="paper experiment 300 ± 75 µm")
    ax.axhline(PAPER_RELEASE_SIMULATION * UM, color="k", ls="--", label="paper simulation 127 µm")
    ax.set_xlabel("robot retreat (µm)")
    ax.set_ylabel("sphere displacement (µm)")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    bx.hist(mc * UM, bins=25, color="C3", alpha=0.7)
    bx.axvspan(225, 375, color="k", alpha=0.1)
    bx.set_xlabel("D_p,r (µm)")
    bx.set_ylabel("trials")
    bx.set_title(f"{n} seeded trials: mobility scatter 20 %, 10 % sticky", fontsize=9)
    return [save_figure(fig, ctx.figure_path("release"), dpi=120)]


def summarise(computed: Computed) -> tuple[list[str], list[PaperRow]]:
    """D_p,r uncalibrated, calibrated and its Monte Carlo spread, against the paper's 127 µm and 300 ± 75 µm."""
    r = computed.results
    d0, d_acc, cal, mc = (r["release_displacement_um"], r["release_displacement_accurate_drag_um"], r["calibrated"],
                          r["monte_carlo"])
    summary = [
        f"- D_p,r uncalibrated: {d0:.0f} µm (paper drag), {d_acc:.0f} µm (accurate drag); "
        "paper: 127 µm simulated, 300 ± 75 µm measured",
        f"- calibrated ε = {cal['release']['roughness_um']:.2f} µm reproduces 300 µm; joint fit ε = "
        f"{cal['joint']['roughness_um']:.2f} µm gives {cal['joint']['release_displacement_um']:.0f} µm",
        f"- Monte Carlo ({mc['trials']} trials, seed {computed.data['seed']}): {mc['mean_um']:.0f} ± "
        f"{mc['std_um']:.0f} µm",
    ]
    paper = [
        PaperRow("D_p,r (simulation)", "127 µm", f"{d0:.0f} µm", "uncalibrated, ε = 25 nm, paper drag"),
        PaperRow("D_p,r (experiment)", "300 ± 75 µm", f"{cal['release']['release_displacement_um']:.0f} µm",
                 f"calibrated ε = {cal['release']['roughness_um']:.2f} µm"),
    ]
    return summary, paper
