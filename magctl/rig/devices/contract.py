"""The contract test of the device interfaces: every camera and coil driver, simulated or real, passes it.

Call :func:`check_camera` or :func:`check_coil_driver` from a test with a function that builds a fresh,
unopened device; each raises :class:`AssertionError` naming the broken rule. magctl runs them on every
adapter it ships (``tests/rig/devices/``); a lab runs them on its own adapter the same way::

    from magctl.rig.devices.contract import check_coil_driver
    def test_my_board():
        check_coil_driver(lambda: MyBoard("/dev/ttyACM0"))
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from magctl.rig.devices.base import Camera, CoilDriver, CoilSetpoint, DeviceError
from magctl.rig.interface import CommandRejected


def _expect(ok: bool, rule: str) -> None:
    if not ok:
        raise AssertionError(rule)


def check_camera(make: Callable[[], Camera], frames: int = 5, timeout: float = 5.0) -> None:
    """A camera delivers grayscale [0, 1] frames of its stated shape with increasing numbers and timestamps, closes
    idempotently and refuses to grab once closed."""
    cam = make()
    _expect(isinstance(cam, Camera), f"{type(cam).__name__} is not a magctl.rig.devices.base.Camera")
    _expect(cam.period > 0, f"{cam.name}: period must be > 0")
    with cam:
        h, w = cam.shape
        last = None
        for _ in range(frames):
            f = cam.grab(timeout)
            _expect(f is not None, f"{cam.name}: no frame within {timeout} s")
            _expect(f.image.shape == (h, w), f"{cam.name}: frame shape {f.image.shape} is not the stated {(h, w)}")
            _expect(f.image.dtype.kind == "f", f"{cam.name}: frames must be float, got {f.image.dtype}")
            _expect(bool(np.all((f.image >= 0) & (f.image <= 1))), f"{cam.name}: pixel values outside [0, 1]")
            if last is not None:
                _expect(f.number > last.number, f"{cam.name}: frame numbers must increase "
                                                f"({last.number} then {f.number})")
                _expect(f.t >= last.t, f"{cam.name}: timestamps must not decrease ({last.t} then {f.t})")
            last = f
    cam.close()  # twice: idempotent
    try:
        cam.grab(0.1)
    except DeviceError:
        pass
    else:
        raise AssertionError(f"{cam.name}: grab after close must raise DeviceError")


def _same(a: CoilSetpoint, b: CoilSetpoint, tol: float) -> bool:
    return bool(np.allclose(a.dc, b.dc, atol=tol) and np.allclose(a.ac, b.ac, atol=tol)
                and abs(a.freq - b.freq) <= max(tol, 1e-3 * abs(b.freq)))


def check_coil_driver(make: Callable[[], CoilDriver], *, wait: Callable[[float], None] | None = None,
                      resolution: float = 1e-3) -> None:
    """A coil driver opens with its outputs at zero, applies and reports setpoints within its ratings, refuses
    setpoints that are not finite, have the wrong channel count or exceed a rating (outputs unchanged), zeroes on
    demand, closes idempotently and refuses writes once closed.

    With ``wait`` (a function that lets that many seconds pass on the device's clock) and a device-side deadline,
    it also checks that the outputs still hold at 0.9 deadline and are zero (and the trip reported) just past one
    deadline after the last setpoint, a read-back in between notwithstanding.
    ``resolution`` is the device's current resolution, A (read-back comparisons allow it).
    """
    drv = make()
    _expect(isinstance(drv, CoilDriver), f"{type(drv).__name__} is not a magctl.rig.devices.base.CoilDriver")
    n = drv.n_channels
    _expect(not drv.device_deadline or (drv.deadline is not None and drv.deadline > 0),
            f"{drv.name}: a device-side deadline needs a deadline > 0 s")
    drv.open()
    try:
        # after open: a driver may learn its ratings from the device
        limit = np.asarray(drv.current_limit, dtype=float)
        _expect(limit.shape == (n,) and bool(np.all(limit > 0)),
                f"{drv.name}: current_limit must be {n} ratings > 0")
        rb = drv.readback()
        _expect(rb is None or rb.setpoint.is_zero(), f"{drv.name}: outputs are not zero after open")
        sign = np.where(np.arange(n) % 2 == 0, 1.0, -1.0)
        good = CoilSetpoint(0.4 * limit * sign, 0.3 * limit * sign[::-1], min(20.0, drv.freq_max))
        drv.write(good)
        rb = drv.readback()
        _expect(rb is None or _same(rb.setpoint, good, resolution),
                f"{drv.name}: read-back {rb and rb.setpoint} is not the setpoint written {good}")
        bad = [CoilSetpoint(np.full(n, np.nan), np.zeros(n), 1.0),
               CoilSetpoint(1.5 * limit, np.zeros(n), 1.0),
               CoilSetpoint(0.6 * limit, 0.6 * limit, 1.0),
               CoilSetpoint(np.zeros(n + 1), np.zeros(n + 1), 1.0),
               CoilSetpoint(np.zeros(n), np.zeros(n), drv.freq_max * 2 + 1)]
        for sp in bad:
            try:
                drv.write(sp)
            except CommandRejected as err:
                _expect(drv.name in str(err), f"{drv.name}: the refusal must name the device: {err}")
            else:
                raise AssertionError(f"{drv.name}: accepted an invalid setpoint {sp}")
            rb = drv.readback()
            _expect(rb is None or _same(rb.setpoint, good, resolution),
                    f"{drv.name}: a refused setpoint changed the outputs")
        drv.zero()
        rb = drv.readback()
        _expect(rb is None or rb.setpoint.is_zero(), f"{drv.name}: outputs not zero after zero()")
        if wait is not None and drv.device_deadline:
            drv.write(good)
            wait(drv.deadline * 0.9)
            rb = drv.readback()
            _expect(rb is None or (_same(rb.setpoint, good, resolution) and not rb.tripped),
                    f"{drv.name}: outputs gone before the deadline")
            # the read-back just sent must not have restarted the deadline
            wait(drv.deadline * 0.15 + 0.01)
            rb = drv.readback()
            _expect(rb is None or (rb.setpoint.is_zero() and rb.tripped),
                    f"{drv.name}: outputs not zero (or trip not reported) one deadline after the last setpoint")
    finally:
        drv.close()
    drv.close()  # twice: idempotent
    try:
        drv.write(CoilSetpoint.zero(n))
    except DeviceError:
        pass
    else:
        raise AssertionError(f"{drv.name}: write after close must raise DeviceError")
