"""VisaCoils against pyvisa-sim's simulated function generators (magctl/rig/devices/visa-sim.yaml)."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

pyvisa = pytest.importorskip("pyvisa")
pytest.importorskip("pyvisa_sim")

from magctl.rig.devices.base import CoilSetpoint, DeviceError  # noqa: E402
from magctl.rig.devices.contract import check_coil_driver  # noqa: E402
from magctl.rig.devices.visa_coils import SIM_DEFINITIONS, SIM_RESOURCES, VisaCoils, sim_backend  # noqa: E402

FG1, FG2, FG3 = SIM_RESOURCES


@pytest.fixture
def backend(tmp_path):
    """A private copy of the definitions: pyvisa keeps one simulated library (and its instruments' settings) per
    definitions path for the whole process."""
    path = tmp_path / "visa-sim.yaml"
    shutil.copy(SIM_DEFINITIONS, path)
    return sim_backend(path)


@pytest.fixture
def ask(backend):
    """Query a simulated instrument directly, as a second VISA session would."""
    rm = pyvisa.ResourceManager(backend)
    opened = {}

    def ask(resource: str, query: str) -> str:
        if resource not in opened:
            opened[resource] = rm.open_resource(resource, read_termination="\n", write_termination="\n")
        return opened[resource].query(query).strip()

    yield ask
    for inst in opened.values():
        inst.close()


def test_visa_coils_keep_the_coil_driver_contract(backend):
    def make():
        return VisaCoils(SIM_RESOURCES, transconductance=[0.5, 1.0, 2.0, 0.5, 1.0, 2.0],
                         current_limit=[2.0, 2.0, 4.0, 1.0, 1.0, 1.0], backend=backend)

    drv = make()
    assert drv.device_deadline is False and drv.deadline is None
    check_coil_driver(make)  # no wait: a function generator has no device-side deadline


def test_a_missing_resource_is_one_line_naming_the_device_and_the_resource(backend):
    missing = "TCPIP0::192.0.2.99::inst0::INSTR"
    drv = VisaCoils((FG1, FG2, missing), 1.0, 1.0, backend=backend, name="coils-A")
    with pytest.raises(DeviceError) as err:
        drv.open()
    msg = str(err.value)
    assert msg.startswith("coils-A: ") and missing in msg and "\n" not in msg
    with pytest.raises(DeviceError, match="not open"):
        drv.write(CoilSetpoint.zero(6))  # what it had opened is released


def test_a_missing_definitions_file_is_one_line_naming_the_backend(tmp_path):
    backend = f"{tmp_path / 'nowhere.yaml'}@sim"
    with pytest.raises(DeviceError) as err:
        VisaCoils(SIM_RESOURCES, 1.0, 1.0, backend=backend).open()
    assert backend in str(err.value) and "nowhere.yaml" in str(err.value) and "\n" not in str(err.value)


@pytest.mark.parametrize("dc, ac, setting", [(6.0, 0.0, "offset"), (0.0, 6.0, "amplitude")])
def test_a_value_the_instrument_refuses_names_instrument_and_channel(backend, ask, dc, ac, setting):
    # 1 A/V and an 8 A rating: the host's check passes, the generator (offset ±5 V, amplitude ≤ 10 Vpp) refuses
    with VisaCoils(SIM_RESOURCES, 1.0, 8.0, backend=backend) as drv:
        sp = CoilSetpoint(np.zeros(6), np.zeros(6), 10.0)
        sp.dc[3], sp.ac[3] = dc, ac  # coil 3: the second generator's channel 2
        with pytest.raises(DeviceError) as err:
            drv.write(sp)
        msg = str(err.value)
        assert f"{FG2} channel 2 (coil 3)" in msg and "-100" in msg and "\n" not in msg, msg
        assert float(ask(FG2, "SOUR2:VOLT:OFFS?")) == 0.0 and float(ask(FG2, "SOUR2:VOLT?")) == 0.0
        drv.zero()
        assert drv.readback().setpoint.is_zero()
        drv.write(CoilSetpoint(np.full(6, 1.0), np.full(6, 0.5), 10.0))  # usable again: sends everything
        assert np.allclose(drv.readback().setpoint.dc, 1.0)


def test_amperes_to_volts_phases_and_channel_map_by_hand(backend, ask):
    # coil k -> (instrument, channel), in reverse; one inverting amplifier (coil 5)
    channels = [(2, 2), (2, 1), (1, 2), (1, 1), (0, 2), (0, 1)]
    g = [0.5, 2.0, 1.0, 4.0, 0.25, -1.0]
    dc = np.array([0.3, -1.0, 0.0, 2.0, 0.05, 0.2])
    ac = np.array([-0.2, 0.5, 0.1, 0.0, -0.05, 0.3])
    # by hand: offset = dc/g; Vpp = 2|ac/g|; phase 180° where ac/g < 0; a zero amplitude keeps phase 0 from open
    expect = [  # (resource, channel, offset V, amplitude Vpp, phase °)
        (FG3, 2, 0.6, 0.8, 180.0),
        (FG3, 1, -0.5, 0.5, 0.0),
        (FG2, 2, 0.0, 0.2, 0.0),
        (FG2, 1, 0.5, 0.0, 0.0),
        (FG1, 2, 0.2, 0.4, 180.0),
        (FG1, 1, -0.2, 0.6, 180.0),
    ]
    with VisaCoils(SIM_RESOURCES, g, 3.0, channels=channels, backend=backend) as drv:
        sp = CoilSetpoint(dc, ac, 12.5)
        drv.write(sp)
        for res, ch, offs, vpp, phase in expect:
            assert float(ask(res, f"SOUR{ch}:VOLT:OFFS?")) == pytest.approx(offs, abs=1e-9)
            assert float(ask(res, f"SOUR{ch}:VOLT?")) == pytest.approx(vpp, abs=1e-9)
            assert float(ask(res, f"SOUR{ch}:PHAS?")) == pytest.approx(phase, abs=1e-9)
            assert float(ask(res, f"SOUR{ch}:FREQ?")) == pytest.approx(12.5)
            assert ask(res, f"OUTP{ch}?") == "ON" and ask(res, f"SOUR{ch}:FUNC?") == "SIN"
        rb = drv.readback().setpoint
        assert np.allclose(rb.dc, dc) and np.allclose(rb.ac, ac) and rb.freq == pytest.approx(12.5)

        drv.write(CoilSetpoint(dc, -ac, 12.5))  # the opposite phase: same amplitudes, phases swapped
        assert float(ask(FG3, "SOUR2:PHAS?")) == 0.0 and float(ask(FG3, "SOUR1:PHAS?")) == 180.0
        assert float(ask(FG3, "SOUR2:VOLT?")) == pytest.approx(0.8)
        assert np.allclose(drv.readback().setpoint.ac, -ac)

        drv.write(CoilSetpoint(dc, ac, 0.0))  # 0 Hz is static: no amplitude, the frequency left as it was
        assert float(ask(FG3, "SOUR2:VOLT?")) == 0.0 and float(ask(FG3, "SOUR2:FREQ?")) == pytest.approx(12.5)
        rb = drv.readback().setpoint
        assert np.allclose(rb.dc, dc) and not np.any(rb.ac) and rb.freq == 0.0


def test_offset_and_amplitude_change_in_the_order_that_stays_within_the_rating(backend):
    with VisaCoils(SIM_RESOURCES, 1.0, 1.0, backend=backend) as drv:
        sent = []
        inst = drv._inst[0]
        write = inst.write
        inst.write = lambda cmd: (sent.append(cmd), write(cmd))[1]

        def order(dc0, ac0):
            sent.clear()
            drv.write(CoilSetpoint([dc0, 0, 0, 0, 0, 0], [ac0, 0, 0, 0, 0, 0], 10.0))
            return [c.split()[0] for c in sent if c.startswith(("SOUR1:VOLT ", "SOUR1:VOLT:OFFS "))]

        order(0.9, 0.0)
        # (0.9, 0) -> (0, 0.9): offset down first; amplitude first would pass through (0.9, 0.9), 1.8 A
        assert order(0.0, 0.9) == ["SOUR1:VOLT:OFFS", "SOUR1:VOLT"]
        # (0, 0.9) -> (0.9, 0): amplitude down first
        assert order(0.9, 0.0) == ["SOUR1:VOLT", "SOUR1:VOLT:OFFS"]
        assert order(0.9, 0.0) == [] and sent == []  # nothing changed, nothing sent
        order(0.0, -0.9)
        assert "SOUR1:PHAS 180" in sent
        order(0.9, 0.0)
        assert not any(c.startswith("SOUR1:PHAS") for c in sent)  # a zero amplitude keeps its phase


def test_zero_keeps_outputs_on_and_close_turns_them_off(backend, ask):
    drv = VisaCoils(SIM_RESOURCES, 1.0, 1.0, backend=backend)
    drv.open()
    drv.write(CoilSetpoint(np.full(6, 0.5), np.full(6, -0.25), 10.0))
    drv.zero()
    assert all(ask(res, f"OUTP{ch}?") == "ON" for res in SIM_RESOURCES for ch in (1, 2))
    assert all(float(ask(res, f"SOUR{ch}:VOLT:OFFS?")) == 0.0 for res in SIM_RESOURCES for ch in (1, 2))
    drv.close()
    assert all(ask(res, f"OUTP{ch}?") == "OFF" for res in SIM_RESOURCES for ch in (1, 2))


def test_readback_refuses_a_phase_that_is_not_a_sign(backend, ask):
    with VisaCoils(SIM_RESOURCES, 1.0, 1.0, backend=backend) as drv:
        drv.write(CoilSetpoint(np.zeros(6), np.full(6, 0.5), 10.0))
        ask(FG2, "SOUR1:PHAS 90;*IDN?")  # a front-panel change behind the driver's back
        with pytest.raises(DeviceError, match=f"{FG2} channel 1 \\(coil 2\\): phase 90"):
            drv.readback()
