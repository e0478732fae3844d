"""The full simulated hardware path of ``examples/lab-sim.toml``: frames rendered from the physical plant and sent
through OpenCV to the image tracker, commands through the serial adapter to the host-compiled firmware behind a
pseudo-terminal, whose outputs drive the plant.

Deterministic: lock-step (the firmware's clock set to each frame's time by the simulated camera). The lab server is
``magctl rig serve --config`` in its own process on loopback, started as a user would.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from magctl.rig.lab import build_station, load_lab
from magctl.rig.log import read_log
from magctl.rig.runtime import Runtime
from magctl.rig.server import start_server
from magctl.rig.station import StationRig

ROOT = Path(__file__).resolve().parents[3]
LAB = ROOT / "examples" / "lab-sim.toml"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class LabServer:
    """``magctl rig serve --config LAB`` in a subprocess."""

    def __init__(self, lab: Path, *extra: str):
        self.address = f"tcp://127.0.0.1:{_free_port()}"
        self.proc = start_server([sys.executable, "-m", "magctl", "rig", "serve", "--config", str(lab), "--bind",
                                  self.address, *extra], cwd=ROOT)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            self.proc.wait(timeout=20)


def _run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "magctl", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=600, stdin=subprocess.DEVNULL)


def _lab(tmp_path: Path, **camera) -> Path:
    text = LAB.read_text()
    extra = "".join(f"{k} = {json.dumps(v)}\n" for k, v in camera.items())
    path = tmp_path / "lab.toml"
    path.write_text(text.replace('encoding = "png"\n', f'encoding = "png"\n{extra}'))
    return path


def _in_process(lab: Path, task: str, options: dict, log: Path, max_ticks: int):
    cfg = load_lab(lab)
    stations = []

    def make():
        stations.append(build_station(cfg, lockstep=True))
        return stations[-1]

    rig = StationRig(make, limits=cfg.limits, watchdog=cfg.watchdog, realtime=False)
    runtime = Runtime(rig, task, options, log_path=log, realtime=False, max_ticks=max_ticks, quiet=True)
    try:
        report = runtime.run()
    finally:
        rig.close()
    return report, stations


def _stable(doc: dict) -> dict:
    drop = {"timing", "run_id", "t_wall", "started", "stopped", "wall"}
    return {k: (_stable(v) if isinstance(v, dict) else v) for k, v in doc.items() if k not in drop}


def test_the_path_is_deterministic_in_lockstep(tmp_path):
    """Two runs through the firmware and the OpenCV path give the same events."""
    logs = []
    for k in range(2):
        log = tmp_path / f"goto{k}.jsonl"
        report, _ = _in_process(LAB, "goto", {"target_um": [1500.0, 1800.0]}, log, 45)
        assert report.exit_status in ("done", "stopped")
        logs.append([_stable(e) for e in read_log(log).events])
    assert logs[0] == logs[1]
    assert logs[0][-1]["obs"]["robot_est_m"][0] > logs[0][0]["obs"]["robot_est_m"][0] + 100e-6  # it drove


class UnpluggingRig(StationRig):
    """Pulls the coil board's cable (kills the firmware's process) before the write of frame ``at``."""

    at = 30

    def _write(self, cmd):
        if self.plant.frame == self.at:
            board = self.plant._closers[0].__self__   # the HostBoard behind the pty
            os.kill(board.pid, 9)
            board.proc.wait(timeout=10)
        return super()._write(cmd)


def test_an_unplugged_board_ends_the_run_and_names_the_board(tmp_path):
    cfg = load_lab(LAB)
    rig = UnpluggingRig(lambda: build_station(cfg, lockstep=True), limits=cfg.limits, watchdog=cfg.watchdog)
    try:
        report = Runtime(rig, "goto", {"target_um": [2000.0, 2500.0]}, log_path=tmp_path / "unplug.jsonl",
                         realtime=False, max_ticks=300, quiet=True).run()
    finally:
        rig.close()
    assert report.exit_status == "error", report.reason
    assert "sim-board" in report.reason
    assert report.ticks <= UnpluggingRig.at + 1


def test_a_dry_run_keeps_the_coils_at_zero(tmp_path):
    server = LabServer(LAB, "--lockstep", "--dry-run")
    try:
        log = tmp_path / "dry.jsonl"
        done = _run_cli("rig", "run", "--rig", server.address, "--task", "goto", "--target-um", "1500", "1800",
                        "--max-ticks", "40", "--log", str(log), "--json")
        assert done.returncode == 0, done.stderr
        events = read_log(log).events
        commanded = [e["cmd"]["b_osc_T"] for e in events if e.get("cmd")]
        assert max(commanded) > 0  # the controller did command a field...
        currents = np.array([e["obs"]["currents_A"] for e in events])
        assert not currents.any()  # ...and the coils never carried it
        start, end = np.array(events[0]["obs"]["robot_est_m"]), np.array(events[-1]["obs"]["robot_est_m"])
        assert np.linalg.norm(end - start) < 5e-6  # so the robot did not move
    finally:
        server.stop()


@pytest.mark.parametrize("task", ["front-push"])
def test_the_log_of_a_lab_run_replays(tmp_path, task):
    log = tmp_path / "r.jsonl"
    _in_process(LAB, task, {}, log, 120)
    done = _run_cli("log", "replay", str(log), "--json")
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["identical"] is True


def test_the_simulated_camera_keeps_the_camera_contract():
    """The simulated camera is checked by the same contract as the OpenCV one."""
    from magctl.rig.devices.base import CoilSetpoint
    from magctl.rig.devices.contract import check_camera
    from magctl.rig.devices.simulated import SimCamera, SimWorld
    from magctl.rig.interface import CoilMap
    from magctl.rig.plant import Scene

    def make():
        world = SimWorld(Scene.default(1), CoilMap.from_coils(), plant="standin")
        return SimCamera(world, lambda t: CoilSetpoint.zero(6), encoding="jpg")

    check_camera(make)


def test_the_host_board_keeps_the_coil_driver_contract_through_the_lab_adapter():
    """The lab's simulated board is the serial adapter on the firmware: the contract with the board's clock driven."""
    from magctl.rig.devices.contract import check_coil_driver
    from magctl.rig.devices.firmware import HostBoard
    from magctl.rig.devices.serial_board import SerialCoilBoard

    with HostBoard(clock="external", deadline=0.1) as board:
        check_coil_driver(lambda: SerialCoilBoard(board.pty, deadline=0.1, name="sim-board"), wait=board.advance)
