"""``magctl stability servo``: the linear 30 Hz servo loop and its simulated step response."""

from __future__ import annotations

from magctl.cli.common import add_json, bounded_float, bounded_int, emit

KP = bounded_float(1e-6, 1e3, "a gain in 1/s")
KI = bounded_float(0.0, 1e4, "a gain in 1/s²")
DELAY = bounded_int(0, 300, "a latency in frames (10 s at 30 Hz)")
STEP_UM = bounded_float(1e-3, 1e4, "a step in µm")


def register_servo(subparsers) -> None:
    """Add ``servo`` to the ``stability`` sub-commands."""
    import tomllib

    from magctl.config import models_dir

    # the settings' names, read without numpy or the servo block (the command checks the file itself)
    try:
        with open(models_dir() / "servo.toml", "rb") as fh:
            settings = sorted(k for k in tomllib.load(fh) if k != "choice")
    except (OSError, tomllib.TOMLDecodeError):
        settings = None
    p = subparsers.add_parser("servo", help="PI visual-servo loop: poles, margins, overshoot (linear vs simulated)")
    p.add_argument("--setting", default=None, choices=settings,
                   help="parameter set from models/servo.toml (default: its [choice] default)")
    p.add_argument("--kp", type=KP, default=None, help="proportional gain, 1/s (overrides the setting)")
    p.add_argument("--ki", type=KI, default=None, help="integral gain, 1/s² (overrides the setting)")
    p.add_argument("--delay-frames", type=DELAY, default=None,
                   help="camera latency in frames (default: camera.toml)")
    p.add_argument("--step-um", type=STEP_UM, default=1000.0,
                   help="target step for the overshoot, µm (default 1000)")
    add_json(p)
    p.set_defaults(func=cmd_servo)


def servo_report(setting: str | None = None, kp: float | None = None, ki: float | None = None,
                 delay_frames: int | None = None, step_um: float = 1000.0) -> dict:
    """Everything ``magctl stability servo`` prints, as a JSON-able dict (µm, s)."""
    from magctl.control.servo import Servo, default_servo_setting, servo_params
    from magctl.core.errors import ParameterError
    from magctl.sensing.camera import camera_params
    from magctl.stability.servo import analyse, step_report

    if not step_um > 0:
        raise ParameterError(f"--step-um {step_um} must be positive")
    setting = setting or default_servo_setting()
    params = servo_params(setting)
    servo = Servo("servo", kp=kp, ki=ki, params=params)
    d = int(camera_params().camera.latency) if delay_frames is None else delay_frames
    report = analyse(servo.kp, servo.ki, d)
    doc = {"setting": setting, "anti_windup": servo.anti_windup, "speed_max_um_s": servo.speed_max * 1e6,
           **report.to_dict(step_um)}
    doc["linear_overshoot_um"] = doc.pop("overshoot_um")
    if report.stable:
        sim = step_report(servo, delay_frames=d, step=step_um * 1e-6)
        doc.update({"sim_overshoot_um": sim["sim_overshoot_um"], "sim_first_arrival_s": sim["first_arrival_s"],
                    "sim_final_error_um": sim["final_error_um"],
                    "linear_range_um": servo.speed_max / servo.kp * 1e6})
    return doc


def cmd_servo(args) -> int:
    doc = servo_report(args.setting, args.kp, args.ki, args.delay_frames, args.step_um)
    emit(args, doc, _summary)
    return 0


def _summary(d: dict) -> str:
    poles = ", ".join(f"{p['re']:.4f}{p['im']:+.4f}j" for p in d["poles"])
    lines = [
        f"servo loop ({d['setting']}): kp = {d['kp_per_s']:g} 1/s, ki = {d['ki_per_s2']:g} 1/s², "
        f"delay = {d['delay_frames']} frames, anti-windup {'on' if d['anti_windup'] else 'off'}",
        f"closed-loop poles: {poles}  ({'stable' if d['stable'] else 'UNSTABLE'})",
        f"gain margin {d['gain_margin']:.3g} at {d['phase_crossover_rad_s']:.3g} rad/s, "
        f"phase margin {d['phase_margin_deg']:.1f}° at {d['gain_crossover_rad_s']:.3g} rad/s",
        f"linear step: overshoot {d['overshoot_percent']:.1f} % = {d['linear_overshoot_um']:.1f} µm on "
        f"{d['step_um']:g} µm, 2 % settling {d['settling_time_s']:.2f} s",
    ]
    if "sim_overshoot_um" in d:
        lines.append(f"simulated step ({d['speed_max_um_s']:g} µm/s cap, linear below "
                     f"{d['linear_range_um']:.0f} µm): overshoot {d['sim_overshoot_um']:.1f} µm, "
                     f"final error {d['sim_final_error_um']:.1f} µm")
    return "\n".join(lines)
