"""D_p,r: how far the sphere follows the robot as it backs away after a front push (paper §IV-D).

The sphere starts against the robot's concave front face; the robot retreats
1.5 mm at 0.4 mm/s. Uncalibrated (ε = 25 nm, paper drag and accurate drag) and
calibrated results are shown side by side, and a seeded Monte Carlo with the
block's variability (mobility scatter, sticky patches) shows the spread.
"""

from __future__ import annotations

import dataclasses

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from magctl.plant.fluid.calibration import PAPER_RELEASE_EXPERIMENT, PAPER_RELEASE_SIMULATION, calibrate  # noqa: E402
from magctl.plant.fluid.params import sphere_params  # noqa: E402
from magctl.plant.fluid.scenarios import release_displacement  # noqa: E402
from magctl.studies.runner import PaperRow, StudyContext, StudyResult  # noqa: E402

NAME = "release"
TITLE = "Release displacement D_p,r after a front push"
ORDER = 31
DEFAULT_TRIALS = 200


def run(ctx: StudyContext) -> StudyResult:
    um = 1e6
    d0, retreat, path0 = release_displacement(return_path=True)
    d_acc = release_displacement(drag_mode="accurate")[0]
    cal = calibrate()
    cases = {"uncalibrated (ε = 25 nm)": (d0[0], path0[:, 0])}
    for k in ("release", "joint"):
        d, _, p = release_displacement(roughness=cal[k], return_path=True)
        cases[f"calibrated ε = {cal[k] * um:.2f} µm ({k})"] = (d[0], p[:, 0])
    # Monte Carlo spread at the D_p,r-matched calibration
    n = ctx.n_trials(DEFAULT_TRIALS)
    varied = dataclasses.replace(sphere_params(), release_scatter=0.2, sticky_probability=0.1)
    mc = release_displacement(batch=n, seed=ctx.seed, roughness=cal["release"], params=varied)

    fig, (ax, bx) = plt.subplots(1, 2, figsize=(10, 4))
    for (label, (d, p)), col in zip(cases.items(), ("C0", "C3", "C2"), strict=True):
        ax.plot(retreat * um, p * um, color=col, label=f"{label}: {d * um:.0f} µm")
    ax.axhspan(225, 375, color="k", alpha=0.1, label="paper experiment 300 ± 75 µm")
    ax.axhline(PAPER_RELEASE_SIMULATION * um, color="k", ls="--", label="paper simulation 127 µm")
    ax.set_xlabel("robot retreat (µm)")
    ax.set_ylabel("sphere displacement (µm)")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    bx.hist(mc * um, bins=25, color="C3", alpha=0.7)
    bx.axvspan(225, 375, color="k", alpha=0.1)
    bx.set_xlabel("D_p,r (µm)")
    bx.set_ylabel("trials")
    bx.set_title(f"{n} seeded trials: mobility scatter 20 %, 10 % sticky", fontsize=9)
    fig.tight_layout()
    path = ctx.figure_path("release")
    fig.savefig(path, dpi=120)
    plt.close(fig)

    results = {
        "release_displacement_um": d0[0] * um,
        "release_displacement_accurate_drag_um": d_acc * um,
        "calibrated": {k: {"roughness_um": cal[k] * um,
                           "release_displacement_um": release_displacement(roughness=cal[k])[0] * um}
                       for k in ("release", "joint")},
        "monte_carlo": {"trials": n, "mean_um": float(mc.mean() * um), "std_um": float(mc.std() * um)},
        "paper": {"simulation_um": PAPER_RELEASE_SIMULATION * um, "experiment_um": PAPER_RELEASE_EXPERIMENT * um,
                  "experiment_spread_um": 75.0},
    }
    summary = [
        f"- D_p,r uncalibrated: {d0[0] * um:.0f} µm (paper drag), {d_acc * um:.0f} µm (accurate drag); "
        "paper: 127 µm simulated, 300 ± 75 µm measured",
        f"- calibrated ε = {cal['release'] * um:.2f} µm reproduces 300 µm; joint fit ε = {cal['joint'] * um:.2f} µm "
        f"gives {results['calibrated']['joint']['release_displacement_um']:.0f} µm",
        f"- Monte Carlo ({n} trials, seed {ctx.seed}): {mc.mean() * um:.0f} ± {mc.std() * um:.0f} µm",
    ]
    paper = [
        PaperRow("D_p,r (simulation)", "127 µm", f"{d0[0] * um:.0f} µm", "uncalibrated, ε = 25 nm, paper drag"),
        PaperRow("D_p,r (experiment)", "300 ± 75 µm",
                 f"{results['calibrated']['release']['release_displacement_um']:.0f} µm",
                 f"calibrated ε = {cal['release'] * um:.2f} µm"),
    ]
    return StudyResult(NAME, results, [path], summary, paper)
