"""One contract, two rigs: the in-process SimRig and the network client of a serve-sim subprocess."""

from __future__ import annotations

import time

import numpy as np
import pytest

from magctl.config import load_model
from magctl.rig.client import RigClient
from magctl.rig.interface import Command, CommandRejected, Lifecycle, RigStateError
from magctl.rig.sim import SimRig

PARAMS = load_model("rig")
PERIOD = 1.0 / PARAMS.runtime.rate


@pytest.fixture(params=["sim", "client"])
def rig(request):
    if request.param == "sim":
        r = SimRig(n_spheres=1)
    else:
        r = RigClient(request.getfixturevalue("server").address, reset=True)
    yield r
    r.close()


def frames(rig, n, cmd=None):
    """Advance ``n`` frames, re-sending ``cmd`` each frame (a network rig runs on its own clock)."""
    obs = None
    for _ in range(n):
        if cmd is not None:
            rig.write(cmd)
        if isinstance(rig, RigClient):
            time.sleep(PERIOD)
        obs = rig.read()
    return obs


def test_lifecycle_gates_reads_and_writes(rig):
    assert rig.state is Lifecycle.UNCONFIGURED
    with pytest.raises(RigStateError, match="unconfigured"):
        rig.read()
    rig.configure()
    assert rig.state is Lifecycle.INACTIVE
    with pytest.raises(RigStateError, match="inactive"):
        rig.write(Command.zero())
    obs = rig.read()
    assert obs.robot_est.shape == (2,) and obs.spheres_est.shape == (1, 2) and obs.currents.shape == (6,)
    assert isinstance(obs.lost, bool)
    rig.activate()
    assert rig.state is Lifecycle.ACTIVE and rig.activation == 1
    rig.write(Command.zero())
    rig.deactivate()
    assert rig.state is Lifecycle.INACTIVE
    with pytest.raises(RigStateError):
        rig.configure()


def test_a_command_moves_the_robot_along_the_static_field(rig):
    rig.configure()
    rig.activate()
    start = rig.read().robot_est
    lim = PARAMS.limits
    heading = np.deg2rad(30.0)
    cmd = Command(3e-3 * np.array([np.cos(heading), np.sin(heading)]), 0.5 * lim.b_osc_max, 50.0)
    obs = frames(rig, 12, cmd)
    step = obs.robot_est - start
    assert np.hypot(*step) > 50e-6
    assert np.arctan2(step[1], step[0]) == pytest.approx(heading, abs=1e-6)
    assert np.max(np.abs(obs.currents)) > 0
    # currents follow the coil map: each x coil carries B_x / (2 k)
    k = PARAMS.coils.xy_pair_field_at_max / (2 * PARAMS.coils.current_max)
    assert obs.currents[0] == pytest.approx(cmd.b_static[0] / (2 * k), rel=1e-9)


def test_an_error_zeroes_the_coils_and_leaves_the_rig_inactive_until_reactivated(rig):
    rig.configure()
    rig.activate()
    rig.write(Command(np.array([3e-3, 0.0]), 3e-3, 50.0))
    frames(rig, 2)
    with pytest.raises(CommandRejected, match="b_static"):
        rig.write(Command(np.array([1.0, 0.0]), 0.0, 0.0))  # 1 T: far beyond every limit
    assert rig.state is Lifecycle.INACTIVE and "b_static" in rig.last_error
    obs = frames(rig, 3)
    np.testing.assert_array_equal(obs.currents, 0.0)
    with pytest.raises(RigStateError):
        rig.write(Command.zero())
    rig.activate()
    assert rig.state is Lifecycle.ACTIVE and rig.activation == 2
    rig.write(Command.zero())


def test_nan_command_is_rejected_and_never_applied(rig):
    rig.configure()
    rig.activate()
    with pytest.raises(CommandRejected, match="finite"):
        rig.write(Command(np.array([np.nan, 0.0]), 0.0, 0.0))
    obs = frames(rig, 2)
    assert np.all(np.isfinite(obs.robot_est))
    np.testing.assert_array_equal(obs.currents, 0.0)
