"""``lab.toml``: a rig built from the device adapters a file names (``magctl rig serve --config``, ``rig run --rig``).

The file has five tables (docs/bring-up.md has a commented example; ``examples/lab-sim.toml`` runs here)::

    [lab]        name, camera_timeout_s
    [camera]     adapter = "opencv" | "sim" | an entry point | "package.module:Class", and the adapter's options
    [tracker]    n_spheres, calibration (a file written by ``magctl rig calibrate camera``), seed
    [coils]      adapter = "serial-board" | "visa" | "sim-board" | an entry point | "package.module:Class",
                 deadline_s and the adapter's options; host_deadline_ok = true to accept a driver with no
                 deadline of its own; calibration (a file written by ``magctl rig calibrate coils``: the
                 lab's coil map becomes the calibrated one)
    [limits]     current_limit_A (per coil, at most its rating), b_static_max_mT, b_osc_max_mT, freq_max_Hz
    [simulation] plant, seed, robot_um, spheres_um — only with the simulated devices; coil_gain, coil_angle_deg
                 (6 each): the simulated coils as built, each coil's field scaled and its in-plane part turned

An adapter is found by name among the shipped ones, then among the ``magctl.rig_devices`` entry points of the
installed packages, then as a dotted path; it is built with the table's other keys as keyword arguments. Every
mistake is one :class:`LabConfigError` line naming the file, the table and the key or device.
"""

from __future__ import annotations

import dataclasses
import importlib
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any

import numpy as np

from magctl.config import load_model, read_toml
from magctl.core.errors import MagctlError
from magctl.rig.devices.base import Camera, CoilDriver, CoilSetpoint, DeviceError
from magctl.rig.interface import CoilMap, RigLimits
from magctl.rig.station import DeviceStation

ENTRY_POINT_GROUP = "magctl.rig_devices"
SHIPPED = {
    "camera": {"opencv": "magctl.rig.devices.opencv_camera:OpenCVCamera", "sim": None},
    "coils": {"serial-board": "magctl.rig.devices.serial_board:SerialCoilBoard",
              "visa": "magctl.rig.devices.visa_coils:VisaCoils", "sim-board": None},
}
TABLES = {
    "lab": {"name": str, "camera_timeout_s": float},
    "tracker": {"n_spheres": int, "calibration": str, "seed": int},
    "limits": {"current_limit_A": list, "b_static_max_mT": float, "b_osc_max_mT": float, "freq_max_Hz": float},
    "simulation": {"plant": str, "seed": int, "robot_um": list, "spheres_um": list, "coil_gain": list,
                   "coil_angle_deg": list},
    "camera": None,   # the adapter's own options
    "coils": None,
}
SIM_CAMERA_KEYS = {"encoding": str, "drop_probability": float, "pixel_size_um": float, "rotation_deg": float,
                   "mirror": bool, "origin_x_um": float, "origin_y_um": float, "stops_after_frame": int}
SIM_BOARD_KEYS = {"deadline_s": float}


class LabConfigError(MagctlError):
    """A lab file is malformed or names a device that cannot be built."""


@dataclasses.dataclass
class LabConfig:
    """A parsed, checked ``lab.toml``."""

    path: Path
    name: str
    camera: dict[str, Any]
    coils: dict[str, Any]
    tracker: dict[str, Any]
    limits: RigLimits
    simulation: dict[str, Any] | None
    camera_timeout: float
    watchdog: float
    period: float

    @property
    def simulated(self) -> bool:
        return self.simulation is not None

    def describe(self) -> dict:
        """For the server's hello: which devices, from which file."""
        return {"kind": f"lab ({self.name})", "config": str(self.path), "camera": self.camera["adapter"],
                "coils": self.coils["adapter"], "simulated": self.simulated}


def _check_type(where: str, key: str, value, kind) -> Any:
    if kind is float and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if kind is not None and not isinstance(value, kind) or (kind in (int, float) and isinstance(value, bool)):
        raise LabConfigError(f"{where} {key}: expected {kind.__name__}, got {value!r}")
    if kind is float and not np.isfinite(value):
        raise LabConfigError(f"{where} {key}: not a finite number ({value!r})")
    return value


def _table(path: Path, doc: dict, name: str, required: bool = False) -> dict:
    if name not in doc:
        if required:
            raise LabConfigError(f"{path}: missing [{name}] table")
        return {}
    table = doc[name]
    if not isinstance(table, dict):
        raise LabConfigError(f"{path}: {name} must be a table ([{name}])")
    spec = TABLES[name]
    if spec is None:
        return dict(table)
    out = {}
    for key, value in table.items():
        if key not in spec:
            raise LabConfigError(f"{path} [{name}] {key}: unknown key (known: {', '.join(spec)})")
        out[key] = _check_type(f"{path} [{name}]", key, value, spec[key])
    return out


def _limits(path: Path, table: dict) -> RigLimits:
    """The rig's limits: ``models/rig.toml`` and the coils' ratings, tightened (never loosened) by ``[limits]``."""
    base = RigLimits.from_params()
    coils = base.coils
    where = f"{path} [limits]"
    limit = coils.current_limit.copy()
    if "current_limit_A" in table:
        req = table["current_limit_A"]
        if len(req) != limit.size or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in req):
            raise LabConfigError(f"{where} current_limit_A: expected {limit.size} numbers (one per coil: "
                                 f"{', '.join(coils.names)}), got {req!r}")
        req = np.asarray(req, dtype=float)
        over = np.flatnonzero(req > coils.current_limit)
        if over.size:
            k = int(over[0])
            raise LabConfigError(f"{where} current_limit_A: coil {coils.names[k]} limit {req[k]:g} A is above its "
                                 f"rating {coils.current_limit[k]:g} A (models/coils.toml)")
        if np.any(req <= 0):
            raise LabConfigError(f"{where} current_limit_A: every limit must be > 0 A, got {req.tolist()}")
        limit = req
    fields = {}
    for key, attr, scale in (("b_static_max_mT", "b_static_max", 1e-3), ("b_osc_max_mT", "b_osc_max", 1e-3),
                             ("freq_max_Hz", "freq_max", 1.0)):
        value = getattr(base, attr)
        if key in table:
            req = table[key] * scale
            if not 0 < req <= value:
                raise LabConfigError(f"{where} {key}: {table[key]:g} must be > 0 and at most the rig's limit "
                                     f"{value / scale:g} (models/rig.toml)")
            value = req
        fields[attr] = value
    return RigLimits(coils=CoilMap(coils.pinv, limit, coils.clamp_gradient, coils.names), **fields)


def _calibrated_coils(path: Path, value, limits: RigLimits) -> RigLimits:
    """``[coils] calibration``: the coil map of a ``magctl rig calibrate coils`` file instead of the model's
    (:func:`magctl.rig.calibrate.load_coil_calibration`); the current limits stay."""
    from magctl.rig.calibrate import CalibrationError, adjusted_coil_map, load_coil_calibration

    if not isinstance(value, str) or not value:
        raise LabConfigError(f"{path} [coils] calibration: expected a file name, got {value!r}")
    cal = Path(value) if Path(value).is_absolute() else path.parent / value
    if not cal.is_file():
        raise LabConfigError(f"{path} [coils] calibration: no such file {cal}")
    try:
        gain, angle = load_coil_calibration(cal, limits.coils.names)
    except CalibrationError as err:
        raise LabConfigError(f"{path} [coils] calibration: {err}") from None
    return dataclasses.replace(limits, coils=adjusted_coil_map(limits.coils, gain, angle))


def load_lab(path) -> LabConfig:
    """Read and check a lab file; every error is one line naming the file, table and key."""
    path = Path(path)
    doc = read_toml(path, "lab file", LabConfigError)
    unknown = sorted(set(doc) - set(TABLES))
    if unknown:
        raise LabConfigError(f"{path}: unknown table [{unknown[0]}] (known: {', '.join(TABLES)})")
    lab = _table(path, doc, "lab")
    camera = _table(path, doc, "camera", required=True)
    coils = _table(path, doc, "coils", required=True)
    tracker = _table(path, doc, "tracker")
    simulation = _table(path, doc, "simulation") if "simulation" in doc else None
    coil_calibration = coils.pop("calibration", None)
    for kind, table in (("camera", camera), ("coils", coils)):
        if not isinstance(table.get("adapter"), str) or not table["adapter"]:
            raise LabConfigError(f"{path} [{kind}] adapter: missing (a shipped adapter: "
                                 f"{', '.join(SHIPPED[kind])}; an entry point; or package.module:Class)")
    sim_devices = [k for k, t in (("camera", camera), ("coils", coils)) if SHIPPED[k].get(t["adapter"], 1) is None]
    if sim_devices and simulation is None:
        raise LabConfigError(f"{path}: the simulated {' and '.join(sim_devices)} need a [simulation] table")
    if simulation is not None and len(sim_devices) != 2:
        raise LabConfigError(f"{path}: [simulation] drives the simulated camera and coil board together: use "
                             f"adapter = \"sim\" in [camera] and \"sim-board\" in [coils]")
    if simulation is not None:
        _check_simulation(path, simulation, camera, coils)
    if "calibration" in tracker:
        cal = Path(tracker["calibration"])
        tracker["calibration"] = cal if cal.is_absolute() else path.parent / cal
        if not tracker["calibration"].is_file():
            raise LabConfigError(f"{path} [tracker] calibration: no such file {tracker['calibration']}")
    n = tracker.get("n_spheres", len(simulation.get("spheres_um", [[0, 0]])) if simulation else 1)
    if not 0 <= n <= 16:
        raise LabConfigError(f"{path} [tracker] n_spheres: {n} is outside 0–16")
    tracker["n_spheres"] = n
    timeout = lab.get("camera_timeout_s", 1.0)
    if not 0 < timeout <= 60:
        raise LabConfigError(f"{path} [lab] camera_timeout_s: {timeout:g} must be in (0, 60] s")
    rig = load_model("rig")
    limits = _limits(path, _table(path, doc, "limits"))
    if coil_calibration is not None:
        limits = _calibrated_coils(path, coil_calibration, limits)
    return LabConfig(path, lab.get("name", path.stem), camera, coils, tracker, limits, simulation, timeout,
                     rig.watchdog.timeout, 1.0 / rig.runtime.rate)


def _check_simulation(path: Path, simulation: dict, camera: dict, coils: dict) -> None:
    where = f"{path} [simulation]"
    from magctl.loops import PLANTS

    if simulation.setdefault("plant", "physics") not in PLANTS:
        raise LabConfigError(f"{where} plant: {simulation['plant']!r} is not one of {', '.join(PLANTS)}")
    for key in ("robot_um",):
        if key in simulation and (len(simulation[key]) != 2 or not all(isinstance(v, int | float)
                                                                        for v in simulation[key])):
            raise LabConfigError(f"{where} {key}: expected [x, y] in µm, got {simulation[key]!r}")
    if "spheres_um" in simulation and not all(isinstance(p, list) and len(p) == 2 for p in simulation["spheres_um"]):
        raise LabConfigError(f"{where} spheres_um: expected a list of [x, y] pairs in µm")
    for key, low, high in (("coil_gain", 0.0, 10.0), ("coil_angle_deg", -180.0, 180.0)):
        value = simulation.get(key)
        if value is not None and (len(value) != 6 or not all(isinstance(v, int | float) and not isinstance(v, bool)
                                                              and low < v <= high for v in value)):
            raise LabConfigError(f"{where} {key}: expected 6 numbers in ({low:g}, {high:g}] (one per coil of "
                                 f"models/coils.toml), got {value!r}")
    for kind, table, keys in (("camera", camera, SIM_CAMERA_KEYS), ("coils", coils, SIM_BOARD_KEYS)):
        for key, value in table.items():
            if key == "adapter":
                continue
            if key not in keys:
                raise LabConfigError(f"{path} [{kind}] {key}: the simulated {kind} has no such option "
                                     f"(known: {', '.join(keys)})")
            table[key] = _check_type(f"{path} [{kind}]", key, value, keys[key])


def resolve_adapter(kind: str, name: str, where: str = "lab.toml"):
    """The adapter class for ``name``: shipped, then an entry point of ``magctl.rig_devices``, then a dotted path."""
    target = SHIPPED[kind].get(name)
    if target is None:
        found = [ep for ep in entry_points(group=ENTRY_POINT_GROUP) if ep.name == name]
        if found:
            try:
                return found[0].load()
            except Exception as err:  # noqa: BLE001 - a broken plug-in is named, not a traceback
                raise LabConfigError(f"{where} [{kind}] adapter {name!r}: entry point failed to load: {err}") from None
        target = name if ":" in name else None
    if target is None:
        raise LabConfigError(f"{where} [{kind}] adapter {name!r}: unknown device (shipped: "
                             f"{', '.join(k for k, v in SHIPPED[kind].items() if v)}; or an entry point of "
                             f"{ENTRY_POINT_GROUP}; or package.module:Class)")
    module, _, attr = target.partition(":")
    try:
        cls = getattr(importlib.import_module(module), attr)
    except ImportError as err:
        raise LabConfigError(f"{where} [{kind}] adapter {name!r}: cannot import {module} ({err}); for the shipped "
                             f"adapters install magctl[hardware]") from None
    except AttributeError:
        raise LabConfigError(f"{where} [{kind}] adapter {name!r}: {module} has no {attr}") from None
    base = Camera if kind == "camera" else CoilDriver
    if not (isinstance(cls, type) and issubclass(cls, base)):
        raise LabConfigError(f"{where} [{kind}] adapter {name!r}: {target} is not a {base.__module__}.{base.__name__}")
    return cls


def _construct(kind: str, cls, options: dict, where: str):
    try:
        return cls(**options)
    except TypeError as err:
        raise LabConfigError(f"{where} [{kind}] {cls.__name__}: {err}") from None
    except (ValueError, DeviceError) as err:
        raise LabConfigError(f"{where} [{kind}] {err}") from None


def _calibration(cfg: LabConfig):
    from magctl.rig.devices.tracking import PixelCalibration

    cal = cfg.tracker.get("calibration")
    return PixelCalibration.identity() if cal is None else PixelCalibration.load(cal)


def build_station(cfg: LabConfig, *, lockstep: bool = False, dry_run: bool = False) -> DeviceStation:
    """The station of a lab file: devices opened, outputs zero, the tracker ready (raises LabConfigError or
    DeviceError naming the device). ``dry_run``: commands are checked and logged, the coils kept at zero."""
    if lockstep and not cfg.simulated:
        raise LabConfigError(f"{cfg.path}: lock-step (simulated time) needs the simulated devices; real devices run "
                             f"in real time")
    if cfg.simulated:
        return _simulated_station(cfg, lockstep, dry_run)
    where = str(cfg.path)
    cam_cls = resolve_adapter("camera", cfg.camera["adapter"], where)
    coil_cls = resolve_adapter("coils", cfg.coils["adapter"], where)
    coil_options = {k: v for k, v in cfg.coils.items() if k not in ("adapter", "host_deadline_ok")}
    coils = _construct("coils", coil_cls, coil_options, where)
    _check_deadline(cfg, coils)
    camera = _construct("camera", cam_cls, {k: v for k, v in cfg.camera.items() if k != "adapter"}, where)
    tracker = _tracker(cfg, camera.period, None)
    return _checked(cfg, DeviceStation(camera, coils, tracker, cfg.limits, lockstep=False, period=cfg.period,
                                       camera_timeout=cfg.camera_timeout, dry_run=dry_run))


def _check_deadline(cfg: LabConfig, coils: CoilDriver) -> None:
    if not coils.device_deadline and cfg.coils.get("host_deadline_ok") is not True:
        raise LabConfigError(f"{cfg.path} [coils] {coils.name}: this driver has no deadline of its own, so the coils "
                             f"stay on if the control computer stops; set host_deadline_ok = true to accept that")


def _checked(cfg: LabConfig, station: DeviceStation) -> DeviceStation:
    """The opened station, once its coil driver's ratings (known after opening) cover the lab's limits."""
    try:
        _check_ratings(cfg, station.coils)
    except BaseException:
        station.close()
        raise
    return station


def _check_ratings(cfg: LabConfig, coils: CoilDriver) -> None:
    where = f"{cfg.path} [coils]"
    if coils.n_channels != cfg.limits.coils.current_limit.size:
        raise LabConfigError(f"{where} {coils.name}: {coils.n_channels} channels, the coil map has "
                             f"{cfg.limits.coils.current_limit.size} coils")
    over = np.flatnonzero(cfg.limits.coils.current_limit > np.asarray(coils.current_limit) * (1 + 1e-9))
    if over.size:
        k = int(over[0])
        raise LabConfigError(f"{where} {coils.name}: coil {cfg.limits.coils.names[k]} may draw "
                             f"{cfg.limits.coils.current_limit[k]:g} A but channel {k} is rated "
                             f"{coils.current_limit[k]:g} A; lower [limits] current_limit_A")


def _tracker(cfg: LabConfig, period: float, scene):
    from magctl.rig.devices.tracking import FrameTracker

    init = {} if scene is None else {"init_robot": scene.robot, "init_heading": scene.heading,
                                     "init_spheres": scene.spheres}
    return FrameTracker(n_spheres=cfg.tracker["n_spheres"], calibration=_calibration(cfg), dt=period,
                        seed=cfg.tracker.get("seed", 0), **init)


def _true_coils(cfg: LabConfig) -> CoilMap:
    """The simulated world's coil map: the model's (models/coils.toml), each coil's field per ampere scaled by
    ``[simulation] coil_gain`` and its in-plane part turned by ``coil_angle_deg`` — the coils as built, which the
    lab's own map (``cfg.limits.coils``) need not know."""
    from magctl.rig.calibrate import adjusted_coil_map

    sim = cfg.simulation
    model = CoilMap.from_coils()
    if "coil_gain" not in sim and "coil_angle_deg" not in sim:
        return model
    return adjusted_coil_map(model, sim.get("coil_gain", [1.0] * 6),
                             np.radians(sim.get("coil_angle_deg", [0.0] * 6)))


def _simulated_station(cfg: LabConfig, lockstep: bool, dry_run: bool) -> DeviceStation:
    """The hardware path with simulated ends: the world and its camera, the host-compiled firmware behind a pty."""
    from magctl.rig.devices.firmware import HostBoard
    from magctl.rig.devices.serial_board import SerialCoilBoard
    from magctl.rig.devices.simulated import SimCamera, SimWorld
    from magctl.rig.devices.tracking import PixelCalibration
    from magctl.rig.plant import Scene

    sim = cfg.simulation
    params = load_model("rig")
    n = cfg.tracker["n_spheres"]
    scene = Scene.default(n, params)
    if "spheres_um" in sim:
        scene = Scene(robot=scene.robot, spheres=np.asarray(sim["spheres_um"], dtype=float).reshape(-1, 2) * 1e-6)
    if "robot_um" in sim:
        scene = dataclasses.replace(scene, robot=np.asarray(sim["robot_um"], dtype=float) * 1e-6)
    if len(scene.spheres) != n:
        raise LabConfigError(f"{cfg.path}: [tracker] n_spheres = {n} but [simulation] spheres_um has "
                             f"{len(scene.spheres)}")
    seed = int(sim.get("seed", 0))
    deadline = float(cfg.coils.get("deadline_s", 0.1))
    board = HostBoard(clock="external" if lockstep else "monotonic", deadline=deadline)
    try:
        world = SimWorld(scene, _true_coils(cfg), params, plant=sim["plant"], seed=seed)
        coils = SerialCoilBoard(board.pty, deadline=deadline, name="sim-board")

        def coil_outputs(t: float) -> CoilSetpoint:
            if lockstep:
                board.set_clock(t)
            return board.setpoint()

        cam = cfg.camera
        geometry = None
        if any(k in cam for k in ("pixel_size_um", "rotation_deg", "mirror", "origin_x_um", "origin_y_um")):
            geometry = PixelCalibration.from_params({k: v for k, v in cam.items() if k != "adapter"
                                                     and k not in ("encoding", "drop_probability",
                                                                   "stops_after_frame")})
        camera = SimCamera(world, coil_outputs, geometry=geometry, encoding=cam.get("encoding", "png"),
                           realtime=not lockstep, period=cfg.period, drop_probability=cam.get("drop_probability"),
                           seed=seed, stops_after_frame=cam.get("stops_after_frame"))
        tracker = _tracker(cfg, cfg.period, scene)
        station = DeviceStation(camera, coils, tracker, cfg.limits, lockstep=lockstep, period=cfg.period,
                                camera_timeout=cfg.camera_timeout, dry_run=dry_run, closers=[board.stop])
    except BaseException:
        board.stop()
        raise
    return _checked(cfg, station)
