"""D_p,r: how far the sphere follows the robot as it backs away after a front push (paper §IV-D).

Two set-ups. The paper's simulation: the sphere starts against the robot's concave
front face and the robot retreats 1.5 mm at 0.4 mm/s from rest
(:func:`magctl.plant.fluid.scenarios.release_displacement`). The task's: the first
attempt of the closed-loop front push, which pushes at 0.4 mm/s, stops by eq 11 while
the servo still overshoots, backs 700 µm at the travel speed and settles before it
measures (:mod:`magctl.studies.release_calibration`). The sphere–glass gap ε is
calibrated where the release happens, in the task, so that its mean is the measured
300 µm; the uncalibrated (ε = 25 nm) predictions of both set-ups stand beside it.
A seeded Monte Carlo of the task's release with the studies' ±10 % mobility scatter
shows the spread.
"""

from __future__ import annotations

from magctl.config import load_model
from magctl.plant.fluid.calibration import PAPER_RELEASE_EXPERIMENT, PAPER_RELEASE_SIMULATION
from magctl.plant.fluid.scenarios import release_displacement
from magctl.studies.release_calibration import calibrate_in_task, in_task_release
from magctl.studies.runner import Computed, PaperRow, StudyContext

NAME = "release"
TITLE = "Release displacement D_p,r after a front push"
ORDER = 31
DEFAULT_TRIALS = 200
SCATTER = 0.1  # the studies' mobility scatter (analysis/front_push.py)


UM = 1e6  # m → µm


def compute(ctx: StudyContext) -> Computed:
    """D_p,r in the paper's set-up and in the task, uncalibrated and calibrated, and the task's spread."""
    d0, retreat, path0 = release_displacement(return_path=True)
    d_paper_drag = release_displacement(drag_mode="paper")[0]
    cal = calibrate_in_task()
    eps = cal["roughness"]
    stored = float(load_model("sphere").calibration.release_roughness)
    d_cal, _, path_cal = release_displacement(roughness=eps, return_path=True)
    cases = {"uncalibrated (ε = 25 nm)": (d0[0], path0[:, 0]),
             f"ε = {eps * UM:.1f} µm (calibrated in the task)": (d_cal[0], path_cal[:, 0])}
    n = ctx.n_trials(DEFAULT_TRIALS)
    mc = in_task_release(stored, trials=n, seed=ctx.seed, scatter=SCATTER)
    results = {
        "paper_setup": {"uncalibrated_um": d0[0] * UM, "uncalibrated_paper_drag_um": d_paper_drag * UM,
                        "calibrated_um": d_cal[0] * UM},
        "in_task": {"uncalibrated_mean_um": cal["uncalibrated"][0] * UM,
                    "uncalibrated_std_um": cal["uncalibrated"][1] * UM,
                    "calibrated_mean_um": cal["calibrated"][0] * UM, "calibrated_std_um": cal["calibrated"][1] * UM,
                    "roughness_um": eps * UM, "stored_roughness_um": stored * UM,
                    "grid_roughness_um": (cal["grid"] * UM).tolist(),
                    "grid_release_um": (cal["grid_release"] * UM).tolist()},
        "monte_carlo": {"trials": n, "scatter": SCATTER, "mean_um": float(mc.pull_back.mean() * UM),
                        "std_um": float(mc.pull_back.std() * UM),
                        "overshoot_mean_um": float(mc.overshoot.mean() * UM)},
        "paper": {"simulation_um": PAPER_RELEASE_SIMULATION * UM, "experiment_um": PAPER_RELEASE_EXPERIMENT * UM,
                  "experiment_spread_um": 75.0},
    }
    return Computed(results, {"retreat_m": retreat, "cases": cases, "monte_carlo_m": mc.pull_back, "seed": ctx.seed})


def draw(computed: Computed, ctx: StudyContext) -> list:
    """Sphere displacement along the retreat for each case, and the Monte Carlo histogram."""
    from magctl.studies.figures import pyplot, save_figure

    plt = pyplot()
    d = computed.data
    retreat, mc, n = d["retreat_m"], d["monte_carlo_m"], computed.results["monte_carlo"]["trials"]
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(10, 4))
    for (label, (disp, p)), col in zip(d["cases"].items(), ("C0", "C3"), strict=True):
        ax.plot(retreat * UM, p * UM, color=col, label=f"{label}: {disp * UM:.0f} µm")
    ax.axhspan(225, 375, color="k", alpha=0.1, label="paper experiment 300 ± 75 µm")
    ax.axhline(PAPER_RELEASE_SIMULATION * UM, color="k", ls="--", label="paper simulation 127 µm")
    ax.set_title("the paper's set-up: 1.5 mm retreat at 0.4 mm/s", fontsize=9)
    ax.set_xlabel("robot retreat (µm)")
    ax.set_ylabel("sphere displacement (µm)")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    bx.hist(mc * UM, bins=25, color="C3", alpha=0.7)
    bx.axvspan(225, 375, color="k", alpha=0.1)
    bx.set_xlabel("D_p,r in the task (µm)")
    bx.set_ylabel("trials")
    bx.set_title(f"closed-loop front push, {n} seeded trials, mobility scatter ±{SCATTER:.0%}", fontsize=9)
    return [save_figure(fig, ctx.figure_path("release"), dpi=120)]


def summarise(computed: Computed) -> tuple[list[str], list[PaperRow]]:
    """D_p,r in both set-ups, uncalibrated and calibrated, against the paper's 127 µm and 300 ± 75 µm."""
    r = computed.results
    ps, it, mc = r["paper_setup"], r["in_task"], r["monte_carlo"]
    summary = [
        f"- paper's set-up (1.5 mm retreat at 0.4 mm/s), uncalibrated ε = 25 nm: D_p,r = "
        f"{ps['uncalibrated_um']:.0f} µm "
        f"(eq 4 as printed: {ps['uncalibrated_paper_drag_um']:.0f} µm); paper: 127 µm simulated",
        f"- in the task (closed-loop front push, 700 µm retract), uncalibrated: {it['uncalibrated_mean_um']:.0f} ± "
        f"{it['uncalibrated_std_um']:.0f} µm",
        f"- calibrated in the task: ε = {it['roughness_um']:.2f} µm gives {it['calibrated_mean_um']:.0f} ± "
        f"{it['calibrated_std_um']:.0f} µm (models/sphere.toml holds {it['stored_roughness_um']:.2f} µm); the same ε "
        f"gives {ps['calibrated_um']:.0f} µm in the paper's set-up",
        f"- Monte Carlo of the task's release ({mc['trials']} trials, seed {computed.data['seed']}, ±"
        f"{mc['scatter']:.0%} mobility scatter): {mc['mean_um']:.0f} ± {mc['std_um']:.0f} µm; the servo's overshoot "
        f"pushes the sphere on {mc['overshoot_mean_um']:.0f} µm after the stop",
    ]
    paper = [
        PaperRow("D_p,r (simulation)", "127 µm", f"{ps['uncalibrated_um']:.0f} µm",
                 "paper's set-up, uncalibrated ε = 25 nm"),
        PaperRow("D_p,r (experiment)", "300 ± 75 µm", f"{mc['mean_um']:.0f} ± {mc['std_um']:.0f} µm",
                 f"in the closed-loop task, ε = {it['stored_roughness_um']:.1f} µm calibrated there "
                 f"(uncalibrated: {it['uncalibrated_mean_um']:.0f} µm)"),
    ]
    return summary, paper
