"""``magctl rig calibrate camera`` and ``magctl rig calibrate coils``: :mod:`magctl.rig.calibrate`, docs/calibration.md.

:func:`add_parsers` adds ``calibrate`` with its two commands to the ``magctl rig`` subparsers.
"""

from __future__ import annotations

import argparse

from magctl.cli.common import (
    add_json,
    bounded_int,
    emit,
    existing_file,
    finite_float,
    output_file,
    positive_float,
    positive_int,
)


def hall_reading(text: str) -> tuple[str, float]:
    """``COIL=VALUE``: a coil's name and its measured in-plane field per ampere, mT/A (> 0)."""
    name, sep, value = text.partition("=")
    if not sep or not name:
        raise argparse.ArgumentTypeError(f"write COIL=VALUE (e.g. xp=0.57), got {text!r}")
    try:
        return name, positive_float(value)
    except argparse.ArgumentTypeError as err:
        raise argparse.ArgumentTypeError(f"{name}: {err}") from None


def add_parsers(subparsers) -> None:
    """``calibrate camera`` and ``calibrate coils`` under ``magctl rig``."""
    c = subparsers.add_parser("calibrate", help="calibrate a lab's camera and coils with the robot and the spheres",
                              description="Calibrate a lab rig (lab.toml) from its own camera and coils; "
                                          "docs/calibration.md.")
    cs = c.add_subparsers(dest="calibrate_command", metavar="WHAT")
    cs.required = True

    cam = cs.add_parser("camera", help="µm per pixel, rotation and mirror of the image against the coil axes",
                        description="Scale from targets of known size (the spheres, 210 µm, or "
                                    "--target-diameter-um), rotation and mirror from the robot's heading under static "
                                    "fields in known directions (coils only, no oscillation: the robot turns in "
                                    "place). Writes a [calibration] file for lab.toml [tracker] calibration.")
    _common(cam)
    cam.add_argument("--target-diameter-um", type=positive_float, default=None, metavar="D",
                     help="diameter of the round targets in view, µm (default: the spheres', models/sphere.toml)")
    cam.add_argument("--field-mT", type=positive_float, default=None, metavar="B",
                     help="static field, mT (default models/robot.toml [drive] static_field, within the lab's limit)")
    cam.add_argument("--directions", type=bounded_int(6, 72, "a number of field directions"), default=8,
                     metavar="N", help="field directions, evenly spaced around the circle (default 8)")
    cam.add_argument("--centre-um", type=finite_float, nargs=2, metavar=("X", "Y"), default=None,
                     help="glass coordinates of the image centre, µm (default: where the lab's current "
                          "calibration puts it; the field directions do not show the origin)")
    cam.set_defaults(func=cmd_calibrate_camera)

    co = cs.add_parser("coils", help="each in-plane coil's field direction and relative gain",
                       description="Drives single in-plane coils and neighbouring pairs with known currents, reads "
                                   "the robot's settled heading through the lab's camera calibration and fits each "
                                   "coil's field direction and gain; the scale stays the model's unless a Hall "
                                   "probe reading is given. The vertical coils (zp, zn) are not calibrated by this "
                                   "method. Writes a file for lab.toml [coils] calibration.")
    _common(co)
    co.add_argument("--current-A", type=positive_float, default=None, metavar="I",
                    help="largest current of a setting, A (default: a single coil's field of about 1.4 mT, at most "
                         "half the coils' rating)")
    co.add_argument("--field-mT-per-A", type=hall_reading, action="append", default=[], metavar="COIL=VALUE",
                    help="a Hall-probe reading of an in-plane coil's field per ampere at the centre, mT/A: sets the "
                         "absolute scale (repeatable)")
    co.set_defaults(func=cmd_calibrate_coils)


def _common(p) -> None:
    p.add_argument("--config", type=existing_file, required=True, metavar="LAB", help="the lab file (lab.toml)")
    p.add_argument("--out", type=output_file, required=True, metavar="FILE", help="calibration file to write (TOML)")
    p.add_argument("--frames", type=positive_int, default=3, help="frames measured per setting (default 3)")
    p.add_argument("--settle-frames", type=positive_int, default=None, metavar="N",
                   help="frames to wait after each field step (default: 12 heading time constants of the model)")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    add_json(p)


def _progress(args):
    return None if (args.quiet or args.json) else (lambda line: print(line, flush=True))


def cmd_calibrate_camera(args) -> int:
    from magctl.rig.calibrate import calibrate_camera, require_target
    from magctl.rig.lab import build_station, load_lab

    cfg = load_lab(args.config)
    require_target(cfg.tracker["n_spheres"], args.target_diameter_um)
    station = build_station(cfg, lockstep=cfg.simulated)  # the simulated devices in lock-step: deterministic
    try:
        result = calibrate_camera(
            station, target_diameter=None if args.target_diameter_um is None else args.target_diameter_um * 1e-6,
            field=None if args.field_mT is None else args.field_mT * 1e-3,
            directions_deg=[360.0 * k / args.directions for k in range(args.directions)], frames=args.frames,
            settle_frames=args.settle_frames,
            centre=None if args.centre_um is None else [v * 1e-6 for v in args.centre_um],
            n_spheres=cfg.tracker["n_spheres"], lab=f"lab {cfg.name!r} ({cfg.path.name})", progress=_progress(args))
    finally:
        station.close()
    result.save(args.out, f"written by magctl rig calibrate camera --config {args.config}\n"
                          f"use it in lab.toml: [tracker] calibration = \"{args.out.name}\"")
    doc = {"out": str(args.out), "lab": str(cfg.path), **result.to_dict()}
    emit(args, doc, _camera_summary)
    return 0


def _camera_summary(d: dict) -> str:
    targets = f"{d['targets']} target{'s' if d['targets'] > 1 else ''}, {d['target_images']} images"
    return "\n".join([
        f"pixel size: {d['pixel_size_um']:.4f} ± {d['pixel_size_se_um']:.4f} µm (the {d['target_diameter_um']:g} µm "
        f"targets measure {d['diameter_px']:.3f} ± {d['diameter_se_px']:.3f} px; {targets})",
        f"rotation: {d['rotation_deg']:.3f} ± {d['rotation_se_deg']:.3f}°, "
        f"{'mirrored' if d['mirror'] else 'not mirrored'} "
        f"(rms heading residual {d['residual_rms_deg']:.2f}° over {len(d['directions_deg'])} field directions; "
        f"{d['other_mirror_rms_deg']:.1f}° {'unmirrored' if d['mirror'] else 'mirrored'})",
        f"origin: ({d['origin_um'][0]:.1f}, {d['origin_um'][1]:.1f}) µm: the image centre at "
        f"({d['centre_um'][0]:.1f}, {d['centre_um'][1]:.1f}) µm",
        f"wrote {d['out']}; use it in lab.toml: [tracker] calibration = \"{d['out']}\""])


def cmd_calibrate_coils(args) -> int:
    from magctl.core.errors import MagctlError
    from magctl.rig.calibrate import calibrate_coils
    from magctl.rig.lab import build_station, load_lab

    hall = {}
    for name, value in args.field_mT_per_A:
        if name in hall:
            raise MagctlError(f"--field-mT-per-A {name}: given twice")
        hall[name] = value
    cfg = load_lab(args.config)
    station = build_station(cfg, lockstep=cfg.simulated)
    try:
        result = calibrate_coils(station, current=args.current_A, hall_mT_per_A=hall, frames=args.frames,
                                 settle_frames=args.settle_frames, lab=f"lab {cfg.name!r} ({cfg.path.name})",
                                 progress=_progress(args))
    finally:
        station.close()
    camera = cfg.tracker.get("calibration")
    through = camera or "the nominal camera geometry (no [tracker] calibration)"
    result.save(args.out, f"written by magctl rig calibrate coils --config {args.config}\n"
                          f"headings read through {through}\n"
                          f"use it in lab.toml: [coils] calibration = \"{args.out.name}\"")
    doc = {"out": str(args.out), "lab": str(cfg.path), "camera_calibration": None if camera is None else str(camera),
           **result.to_dict()}
    emit(args, doc, _coils_summary)
    return 0


def _coils_summary(d: dict) -> str:
    lines = [f"{'coil':5} {'gain vs model':>18} {'angle vs model':>16} {'direction (model)':>20} "
             f"{'field at 1 A (model)':>22}"]
    for name, c in d["coils"].items():
        if not c["calibrated"]:
            lines.append(f"{name:5} not calibrated: a vertical coil makes no in-plane field at the centre, so the "
                         "heading does not respond to it (kept as models/coils.toml)")
            continue
        angle = f"{c['angle_deg']:+.2f} ± {c['angle_se_deg']:.2f}°"
        lines.append(f"{name:5} {c['gain']:>9.4f} ± {c['gain_se']:<6.4f} {angle:>16} "
                     f"{c['direction_deg']:>8.2f}° ({c['model_direction_deg']:7.2f}°) "
                     f"{c['field_at_1A_mT']:>8.4f} mT ({c['model_field_at_1A_mT']:.4f})")
    lines.append(f"scale: {d['scale']}")
    lines.append(f"rms heading residual {d['residual_rms_deg']:.2f}° over {d['settings']} settings")
    if d.get("camera_calibration") is None:
        lines.append("note: the lab has no camera calibration ([tracker] calibration): headings were read through "
                     "the nominal camera geometry; run magctl rig calibrate camera first")
    lines.append(f"wrote {d['out']}; use it in lab.toml: [coils] calibration = \"{d['out']}\"")
    return "\n".join(lines)
