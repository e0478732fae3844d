"""Actuator study: speed versus field frequency and the heading step response (plant front half).

Every curve is simulated through the blocks (coils → robot, or drive → coils → robot), with the
frequencies or cases laid along the trial axis, and compared with the closed forms of
docs/plant-actuator.md.
"""

from __future__ import annotations

import numpy as np

from magctl import FRAME_PERIOD_S
from magctl.core import Diagram, simulate
from magctl.plant.coils import CoilActuator, load_coils
from magctl.plant.drive import Drive, actuated_robot, load_drive
from magctl.plant.robot import StickSlipRobot, heading_time_constant, load_robot
from magctl.studies.runner import Computed, PaperRow, StudyContext

NAME = "actuator"
TITLE = "Coil actuator and stick-slip robot: speed–frequency curve and heading response"
ORDER = 5

PAPER_SPEED = 0.4e-3  # paper §IV-C
PAPER_TILT = np.pi / 8  # paper §IV-C
CST_TO_PA_S = 1e-6 * 950.0  # 20 cSt silicone oil at 950 kg/m³ (models/fluid.toml)
STRONG_OSC_FIELD = 8e-3  # T: a rocking command the vertical coils' voltage limit attenuates at high frequency
WEAK_FIELD_FRACTION = 0.1  # heading step also at this fraction of the static field


def coils_and_robot(robot_params, coils) -> Diagram:
    act = CoilActuator("coils", coils)
    bot = StickSlipRobot("robot", robot_params, variability=False)
    return Diagram(
        "front", [act, bot],
        connections=[("coils.b_static_delivered", "robot.b_static_delivered"),
                     ("coils.b_osc_delivered", "robot.b_osc_delivered"),
                     ("coils.freq_delivered", "robot.freq_delivered")],
        inputs={"b_static": "coils.b_static", "b_osc": "coils.b_osc", "freq": "coils.freq"},
        outputs={"velocity": "robot.velocity", "tilt": "robot.tilt", "b_osc": "coils.b_osc_delivered",
                 "saturated": "coils.saturated"},
    )


def speed_curve(robot_params, coils, b_static, b_osc, freqs, steps=4):
    """Simulated steady speed, tilt, delivered b_osc and saturation; one trial per frequency."""
    n = len(freqs)
    res = simulate(coils_and_robot(robot_params, coils), steps, batch=n,
                   inputs={"b_static": [b_static, 0.0], "b_osc": b_osc,
                           "freq": np.tile(np.asarray(freqs)[:, None], (1, steps))})
    o = res.outputs
    return (np.linalg.norm(o["velocity"][:, -1], axis=1), o["tilt"][:, -1], o["b_osc"][:, -1],
            o["saturated"][:, -1])


def compute(ctx: StudyContext) -> Computed:
    """Speed–frequency curves (20/50 cSt, coil-limited strong command), the nominal drive chain, heading steps."""
    robot, coils, drive_set = load_robot(), load_coils(), load_drive()
    drive = Drive("drive", robot, coils, drive_set)
    b0, bo = drive_set.static_field, drive_set.osc_field
    freqs = np.geomspace(0.5, 2000.0, 400)

    v20, tilt20, _, _ = speed_curve(robot, coils, b0, bo, freqs)
    v50, _, _, _ = speed_curve(robot.with_viscosity(50 * CST_TO_PA_S), coils, b0, bo, freqs)
    v_strong, _, _, sat_strong = speed_curve(robot, coils, b0, STRONG_OSC_FIELD, freqs)
    k = int(np.argmax(v20))
    f_att = float(freqs[np.argmax(sat_strong)]) if sat_strong.any() else float("nan")

    # closed-loop-free chain at the paper's speed: drive → coils → robot
    chain = actuated_robot(variability=False)
    steps = 90
    res = simulate(chain, steps, batch=1, inputs={"speed": PAPER_SPEED, "heading": 0.0})
    pos = res.outputs["position"][0]
    v_nom = float((pos[-1, 0] - pos[30, 0]) / ((steps - 1 - 30) * FRAME_PERIOD_S))
    tilt_nom = float(res.outputs["tilt"][0, -1])

    # heading step response: 90° turn of the aligning field, nominal and weak field
    fields = np.array([b0, WEAK_FIELD_FRACTION * b0])
    hsteps = 12
    bot = StickSlipRobot("robot", robot, variability=False)
    hd = Diagram("h", [bot], inputs={"b": "robot.b_static_delivered", "bo": "robot.b_osc_delivered",
                                     "f": "robot.freq_delivered"}, outputs={"heading": "robot.heading"})
    hres = simulate(hd, hsteps, batch=2, inputs={"b": np.stack([0 * fields, fields], 1), "bo": 0.0, "f": 0.0})
    taus = heading_time_constant(robot, fields)

    results = {
        "static_field_mT": b0 * 1e3,
        "osc_field_mT": bo * 1e3,
        "nominal_frequency_Hz": drive.nominal_freq,
        "nominal_speed_um_s": v_nom * 1e6,
        "nominal_tilt_rad": tilt_nom,
        "peak_frequency_Hz": float(freqs[k]),
        "peak_speed_um_s": float(v20[k] * 1e6),
        "peak_speed_50cSt_um_s": float(v50.max() * 1e6),
        "stop_frequency_Hz": float(freqs[np.nonzero(v20 > 0)[0][-1]]),
        "strong_command_saturates_above_Hz": f_att,
        "heading_time_constant_s": float(taus[0]),
        "heading_time_constant_weak_field_s": float(taus[1]),
        "coil_time_constants_s": [c.time_constant for c in coils.coils],
        "drive_max_speed_um_s": drive_set.max_speed * 1e6,
        "frequencies_Hz": freqs[::20].tolist(),
        "speed_20cSt_um_s": (v20[::20] * 1e6).tolist(),
        "tilt_20cSt_rad": tilt20[::20].tolist(),
    }
    data = {"freqs_Hz": freqs, "v20_m_s": v20, "v50_m_s": v50, "v_strong_m_s": v_strong, "peak_index": k,
            "static_field_T": b0, "osc_field_T": bo, "nominal_freq_Hz": drive.nominal_freq,
            "v_nominal_m_s": v_nom, "tilt_nominal_rad": tilt_nom,
            "heading_t_s": np.arange(hsteps) * FRAME_PERIOD_S, "heading_rad": hres.outputs["heading"],
            "heading_fields_T": fields, "heading_taus_s": taus}
    return Computed(results, data)


def heading_closed_form(t, tau):
    """Heading after the aligning field turns by 90° at t = 0 from heading 0: ``π/2 + 2 atan(tan(−π/4) e^(−t/τ))``.

    The solution of ``τ ψ' = sin(π/2 − ψ)``, the overdamped alignment of the magnet with the field.
    """
    return np.pi / 2 + 2 * np.arctan(np.tan(-np.pi / 4) * np.exp(-np.asarray(t) / tau))


def draw(computed: Computed, ctx: StudyContext) -> list:
    """Speed versus frequency, and the heading step against its closed form."""
    from magctl.studies.figures import pyplot, save_figure

    plt = pyplot()
    d = computed.data
    freqs, b0, bo = d["freqs_Hz"], d["static_field_T"], d["osc_field_T"]
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    ax = axes[0]
    ax.semilogx(freqs, d["v20_m_s"] * 1e3, label="20 cSt (paper's oil)")
    ax.semilogx(freqs, d["v50_m_s"] * 1e3, label="50 cSt")
    ax.semilogx(freqs, d["v_strong_m_s"] * 1e3, "--",
                label=f"20 cSt, b_osc = {STRONG_OSC_FIELD * 1e3:.0f} mT (coil-limited)")
    ax.axhline(PAPER_SPEED * 1e3, color="k", lw=0.8, ls=":", label="paper: 0.4 mm/s")
    ax.axvline(d["nominal_freq_Hz"], color="grey", lw=0.8, ls=":")
    ax.set_xlabel("field frequency (Hz)")
    ax.set_ylabel("robot speed (mm/s)")
    ax.set_title(f"Speed vs frequency (B0 = {b0 * 1e3:.1f} mT, b_osc = {bo * 1e3:.2f} mT)")
    ax.legend(fontsize=8)
    ax = axes[1]
    t = d["heading_t_s"]
    tf = np.linspace(0, t[-1], 400)
    for j, (b, tau) in enumerate(zip(d["heading_fields_T"], d["heading_taus_s"])):
        (line,) = ax.plot(tf * 1e3, np.degrees(heading_closed_form(tf, tau)), lw=1,
                          label=f"closed form, |B| = {b * 1e3:.1f} mT, τ = {tau * 1e3:.1f} ms")
        ax.plot(t * 1e3, np.degrees(d["heading_rad"][j]), "o", ms=4, color=line.get_color(),
                label=f"block at 30 Hz, |B| = {b * 1e3:.1f} mT")
    ax.set_xlabel("time (ms)")
    ax.set_ylabel("heading (deg)")
    ax.set_title("Heading after a 90° turn of the field")
    ax.legend(fontsize=8)
    fig_path = save_figure(fig, ctx.figure_path("actuator"), dpi=110)
    return [fig_path]


def summarise(computed: Computed) -> tuple[list[str], list[PaperRow]]:
    """Nominal speed and tilt, the speed peak, the coil limit and the heading time constants against §II, §IV-C."""
    r, d = computed.results, computed.data
    v20, v50, k, freqs = d["v20_m_s"], d["v50_m_s"], d["peak_index"], d["freqs_Hz"]
    v_nom, tilt_nom = d["v_nominal_m_s"], d["tilt_nominal_rad"]
    taus, fields = d["heading_taus_s"], d["heading_fields_T"]
    b0, f_att, tau_coils = d["static_field_T"], r["strong_command_saturates_above_Hz"], r["coil_time_constants_s"]
    summary = [
        f"- Nominal command {PAPER_SPEED * 1e3:.1f} mm/s → {d['nominal_freq_Hz']:.1f} Hz; simulated "
        f"{v_nom * 1e3:.3f} mm/s, mean tilt {tilt_nom:.3f} rad (paper π/8 = {PAPER_TILT:.3f}).",
        f"- Speed peaks at {v20[k] * 1e3:.2f} mm/s at {freqs[k]:.0f} Hz (20 cSt), "
        f"{v50.max() * 1e3:.2f} mm/s at 50 cSt; stops above {r['stop_frequency_Hz']:.0f} Hz "
        "when the rocking lag drops below the break-away angle.",
        f"- A {STRONG_OSC_FIELD * 1e3:.0f} mT rocking command is voltage-limited by the vertical coils above "
        f"{f_att:.0f} Hz (saturated flag set).",
        f"- Heading time constant {taus[0] * 1e3:.1f} ms at {b0 * 1e3:.1f} mT "
        f"({taus[1] * 1e3:.0f} ms at {fields[1] * 1e3:.1f} mT); coil L/R "
        f"{min(tau_coils) * 1e3:.1f}–{max(tau_coils) * 1e3:.1f} ms.",
    ]
    paper = [
        PaperRow("robot speed in experiments", "0.4 mm/s (§IV-C)", f"{v_nom * 1e3:.3f} mm/s",
                 "drive's nominal command through coils and robot"),
        PaperRow("mean robot tilt while rocking", "π/8 = 0.393 rad (§IV-C)", f"{tilt_nom:.3f} rad",
                 "cycle-mean |pitch| at the nominal command"),
        PaperRow("works in fluids up to", "~50 cSt (§II)", f"{v50.max() * 1e3:.2f} mm/s peak at 50 cSt",
                 "speed ∝ 1/viscosity at the peak"),
        PaperRow("top speed in oil", "~4 mm/s (Mag-µBot literature)", f"{v20[k] * 1e3:.2f} mm/s",
                 "calibrated lower; the drive needs only ≤ 1 mm/s"),
    ]
    return summary, paper
