"""Lab files (``magctl rig serve --config``): every mistake is one line naming the file, table and key or device,
a non-zero exit and no server; an adapter of the lab's own plugs in by dotted path.

Each bad case runs ``python -m magctl rig serve --config BAD.toml`` in a subprocess, as a user would.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from magctl.rig.lab import LabConfigError, build_station, load_lab

ROOT = Path(__file__).resolve().parents[3]
SIM = (ROOT / "examples" / "lab-sim.toml").read_text()


def _serve(config: Path, *extra: str, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "magctl", "rig", "serve", "--config", str(config),
                           "--bind", "tcp://127.0.0.1:1", *extra], cwd=ROOT, capture_output=True, text=True,
                          timeout=120, stdin=subprocess.DEVNULL, env={**os.environ, **(env or {})})


def _one_line(done: subprocess.CompletedProcess, *names: str) -> str:
    assert done.returncode == 2, (done.returncode, done.stdout)  # docs/bring-up.md: "exit status 2"
    assert "Traceback" not in done.stderr, done.stderr
    lines = done.stderr.splitlines()
    assert len(lines) == 1, done.stderr
    for name in names:
        assert name in lines[0], lines[0]
    return lines[0]


REAL = """
[camera]
adapter = "opencv"
source = "{video}"

[coils]
adapter = "serial-board"
{coils}
"""

CASES = {
    "unknown device": (REAL.format(video="x.avi", coils='port = "/dev/ttyACM0"').replace('"opencv"', '"frobnicator"'),
                       ["[camera]", "frobnicator", "unknown device"]),
    "missing port": (REAL.format(video="x.avi", coils=""), ["[coils]", "SerialCoilBoard", "port"]),
    "limit above a coil's rating": (SIM + "\n[limits]\ncurrent_limit_A = [3.5, 3, 3, 3, 2, 2]\n",
                                    ["[limits]", "current_limit_A", "xp", "rating"]),
    "unknown table": (SIM + "\n[camra]\nx = 1\n", ["[camra]", "unknown table"]),
    "unknown key": (SIM.replace("camera_timeout_s", "camera_timeout"), ["[lab]", "camera_timeout", "unknown key"]),
    "a string for a number": (SIM.replace("camera_timeout_s = 1.0", 'camera_timeout_s = "slow"'),
                              ["[lab]", "camera_timeout_s", "expected float"]),
    "no camera table": ("[coils]\nadapter = \"sim-board\"\n", ["missing [camera]"]),
    "not TOML": ("[camera\nadapter = sim", ["not valid TOML"]),
    "simulated devices without a world": (SIM.split("[simulation]")[0], ["[simulation]"]),
    "a dotted path that is not a device": (REAL.format(video="x.avi", coils='port = "x"').replace(
        '"opencv"', '"magctl.rig.lab:load_lab"'), ["[camera]", "is not a", "Camera"]),
}


@pytest.mark.parametrize("case", list(CASES))
def test_a_malformed_lab_file_is_one_line_naming_it(tmp_path, case):
    text, names = CASES[case]
    lab = tmp_path / "lab.toml"
    lab.write_text(text)
    line = _one_line(_serve(lab), str(lab), *names)
    assert "error" in line


def test_an_unplugged_board_is_one_line_naming_the_device_and_port(tmp_path):
    video = tmp_path / "v.avi"
    _write_video(video)
    lab = tmp_path / "lab.toml"
    lab.write_text(REAL.format(video=video, coils='port = "/dev/ttyMAGCTL-NONE"'))
    _one_line(_serve(lab), "coil-board", "/dev/ttyMAGCTL-NONE")


def test_a_camera_that_is_not_there_is_one_line_naming_it(tmp_path):
    lab = tmp_path / "lab.toml"
    lab.write_text(REAL.format(video=tmp_path / "missing.avi", coils='port = "loop://"'))
    _one_line(_serve(lab), "camera", "missing.avi")


def test_a_driver_without_its_own_deadline_needs_consent(tmp_path):
    from magctl.rig.devices.visa_coils import SIM_RESOURCES, sim_backend

    video = tmp_path / "v.avi"
    _write_video(video)
    visa = f"""
[camera]
adapter = "opencv"
source = "{video}"

[coils]
adapter = "visa"
backend = "{sim_backend()}"
resources = {list(SIM_RESOURCES)!r}
transconductance = [0.5, 0.5, 0.5, 0.5, 0.5, 0.5]
current_limit = [3.0, 3.0, 3.0, 3.0, 2.0, 2.0]
""".replace("'", '"')
    lab = tmp_path / "lab.toml"
    lab.write_text(visa)
    _one_line(_serve(lab), "[coils]", "no deadline of its own", "host_deadline_ok")
    cfg = load_lab(lab)
    with pytest.raises(LabConfigError, match="host_deadline_ok"):
        build_station(cfg)
    # with consent the VISA generators (pyvisa-sim's instruments) drive the coils
    lab.write_text(visa + "host_deadline_ok = true\n")
    station = build_station(load_lab(lab))
    try:
        from magctl.rig.interface import Command

        station.apply(Command.from_values([1e-3, 0.0], 0.0, 0.0), 0.0)
        assert station.coils.readback().setpoint.peak().max() > 0
        station.zero()
        assert station.coils.readback().setpoint.is_zero()
    finally:
        station.close()


def _write_video(path: Path, n: int = 5) -> None:
    import numpy as np

    from magctl.rig.devices.video import write_video
    from magctl.sensing.camera import camera_params, render_frame

    p = camera_params()
    s = p.camera.pixel_size
    frames = [render_frame(np.array([2e-3, 1.8e-3]), 0.0, np.array([[3e-3, 1.8e-3]]), p.render, pixel=s,
                           width=int(p.camera.width), height=int(p.camera.height)) for _ in range(n)]
    write_video(path, frames, 30.0)


PLUGIN = '''
"""A lab's own coil driver, outside magctl: it plugs in by dotted path."""
import numpy as np
from magctl.rig.devices.base import CoilDriver, CoilReadback, CoilSetpoint, DeviceError


class RecordingCoils(CoilDriver):
    name = "recording-coils"
    device_deadline = True
    deadline = 0.1

    def __init__(self, rating_A=3.0):
        self.current_limit = np.full(6, float(rating_A))
        self.written = []
        self._open = False

    def open(self):
        self._open = True
        self.out = CoilSetpoint.zero(6)

    def write(self, setpoint):
        if not self._open:
            raise DeviceError(self.name, "closed")
        setpoint.check(self.current_limit, self.freq_max, self.name)
        self.written.append(setpoint)
        self.out = setpoint

    def zero(self):
        self.out = CoilSetpoint.zero(6)

    def readback(self):
        return CoilReadback(self.out)

    def close(self):
        self._open = False
'''


def test_a_labs_own_adapter_plugs_in_by_dotted_path_and_keeps_the_contract(tmp_path, monkeypatch):
    from magctl.rig.devices.contract import check_coil_driver
    from magctl.rig.interface import Command

    (tmp_path / "mylab_coils.py").write_text(textwrap.dedent(PLUGIN))
    monkeypatch.syspath_prepend(str(tmp_path))
    import mylab_coils

    check_coil_driver(lambda: mylab_coils.RecordingCoils())
    video = tmp_path / "v.avi"
    _write_video(video)
    lab = tmp_path / "lab.toml"
    lab.write_text(REAL.format(video=video, coils="rating_A = 3.0").replace('"serial-board"',
                                                                            '"mylab_coils:RecordingCoils"'))
    station = build_station(load_lab(lab))
    try:
        cmd = Command.from_values([1e-3, 0.0], 0.0, 0.0)
        station.apply(cmd, 0.0)
        assert station.coils.written[-1].peak().max() > 0
    finally:
        station.close()
    # ratings below what the lab's limits allow are refused once the driver is open
    lab.write_text(REAL.format(video=video, coils="rating_A = 1.0").replace('"serial-board"',
                                                                            '"mylab_coils:RecordingCoils"'))
    with pytest.raises(LabConfigError, match="rated 1 A"):
        build_station(load_lab(lab))


def test_a_labs_own_adapter_plugs_in_by_entry_point(tmp_path, monkeypatch):
    """An installed package declaring ``[magctl.rig_devices] recording = mylab_coils:RecordingCoils``."""
    from magctl.rig.lab import resolve_adapter

    (tmp_path / "mylab_coils.py").write_text(textwrap.dedent(PLUGIN))
    info = tmp_path / "mylab-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: mylab\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[magctl.rig_devices]\nrecording = mylab_coils:RecordingCoils\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    cls = resolve_adapter("coils", "recording")
    assert cls.__name__ == "RecordingCoils" and cls.__module__ == "mylab_coils"
    with pytest.raises(LabConfigError, match="unknown device"):
        resolve_adapter("coils", "no-such-plug-in")
