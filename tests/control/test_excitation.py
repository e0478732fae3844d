"""The identify task's open-loop sweep: its schedule, its headings, its segment index, its speed-limited segments and
its safety stops, the block driven directly with synthetic observations. Every expected number comes from
``models/identify.toml`` ``[experiment]``, ``models/robot.toml`` and ``models/camera.toml``."""

import math

import numpy as np
import pytest

from magctl import FRAME_PERIOD_S as DT
from magctl.config import load_model
from magctl.control.excitation import Excitation, ExcitationParams, inside_field, square_start
from magctl.control.status import Status
from magctl.core.errors import MagctlError
from magctl.plant.drive import load_drive
from magctl.plant.robot import load_robot, steady_speed
from magctl.sensing.camera import field_of_view

E = load_model("identify").experiment
COMMON = load_model("push").common   # the clearance and field margin the sweep keeps
B0 = load_drive().static_field
W, H = field_of_view()
ROBOT = np.array([1.0e-3, 1.8e-3])
SPHERE = np.array([2.0e-3, 1.8e-3])  # 1 mm ahead of the robot along +x: the default scene (models/rig.toml)


def _obs(robot=ROBOT, spheres=(SPHERE,), heading=0.0, lost=False):
    sph = np.asarray(spheres, dtype=float).reshape(1, -1, 2)
    return {"robot_est": np.asarray(robot, dtype=float).reshape(1, 2), "heading_est": np.array([heading]),
            "spheres_est": sph, "lost": np.array([lost])}


def _run(block, frames, obs=None, at=None):
    """Step ``block`` for ``frames`` frames; ``obs`` the observation every frame, or ``at(k)`` per frame."""
    state = block.initial_state(1)
    rows = []
    for k in range(frames):
        out, state = block.step(state, at(k) if at is not None else (obs or _obs()))
        rows.append({n: np.asarray(v)[0].copy() for n, v in out.items()})
    return rows


def _frames(seconds):
    return int(round(seconds / DT))


def _expected_cells():
    """(f, b_osc, frames, speed) of every kept cell, frequency major, from the file and the robot model."""
    robot = load_robot()
    most, least = _frames(E.segment), _frames(E.min_segment)
    cells = []
    for f in E.frequencies:
        for b in E.b_osc:
            v = float(steady_speed(robot, B0, b, f))
            n = most if v <= 0 else min(most, math.floor(E.side_max / (v * DT)))
            if n >= least:
                cells.append((float(f), float(b), n, v))
    return cells


@pytest.fixture(scope="module")
def block():
    return Excitation("task", n_spheres=1)


@pytest.fixture(scope="module")
def sweep(block):
    """The whole default sweep from the default scene, the robot kept where it starts."""
    return _run(block, block.total_frames + 3)


def test_the_grid_spans_the_threshold_and_the_peak_within_the_rig_limits():
    robot, lim = load_robot(), load_model("rig").limits
    f = np.asarray(E.frequencies)
    for b in E.b_osc:  # the speed peak lies inside the frequency range at every amplitude that moves the robot
        fine = np.linspace(f.min(), f.max(), 2001)
        v = steady_speed(robot, B0, b, fine)
        if v.max() > 0:
            assert f.min() < fine[np.argmax(v)] < f.max()
    # the smallest amplitude moves the robot at the lowest frequency and not at the highest: it spans the threshold
    b_low = min(E.b_osc)
    assert steady_speed(robot, B0, b_low, f.min()) > 0 and steady_speed(robot, B0, b_low, f.max()) == 0
    # break_angle: the quasi-static threshold amplitude B0·tan θ0 lies below the smallest amplitude
    assert B0 * math.tan(robot.break_angle) < b_low
    # well inside the rig's limits
    assert max(E.b_osc) <= lim.b_osc_max / 2 and max(E.frequencies) <= 0.75 * lim.freq_max
    assert B0 <= 0.75 * lim.b_static_max


def test_schedule_durations_segments_and_their_speed_limited_length(block):
    cells = _expected_cells()
    segs = block.segments()
    hold, pause = _frames(E.hold), _frames(E.pause)
    assert len(segs) == 4 * len(cells) and [s.index for s in segs] == list(range(len(segs)))
    k = hold
    for c, (f, b, n, v) in enumerate(cells):
        for j in range(4):
            s = segs[4 * c + j]
            k += pause
            assert (s.freq, s.b_osc, s.cell, s.side, s.start, s.frames) == (f, b, c, j, k, n)
            assert s.speed == pytest.approx(v)
            assert s.speed * s.frames * DT <= E.side_max * (1 + 1e-12)
            assert s.frames * DT <= E.segment + 1e-9
            k += n
    assert block.total_frames == k and block.duration == pytest.approx(k * DT)
    # some cells are shortened by side_max, some are left out by min_segment, some drive for the whole segment
    assert any(n < _frames(E.segment) for *_, n, _ in cells)
    assert any(n == _frames(E.segment) for *_, n, _ in cells)
    assert len(cells) < len(E.frequencies) * len(E.b_osc)


def test_hold_pause_drive_commands_headings_and_segment_index(block, sweep):
    segs = block.segments()
    hold, pause = _frames(E.hold), _frames(E.pause)
    # the hold: coils off
    for row in sweep[:hold]:
        assert np.all(row["b_static"] == 0) and row["b_osc"] == 0 and row["freq"] == 0 and row["segment"] == -1
        assert row["status"] == Status.RUNNING
    theta0 = math.pi  # away from the sphere 1 mm along +x

    def heading(row):
        return math.atan2(row["b_static"][1], row["b_static"][0])

    turn = round(math.sin(heading(sweep[segs[1].start]) - theta0))
    assert turn in (-1, 1)
    for s in segs:
        drive = sweep[s.start: s.start + s.frames]
        before = sweep[s.start - pause: s.start]
        for row in drive:
            assert row["segment"] == s.index and row["b_osc"] == s.b_osc and row["freq"] == s.freq
            assert np.hypot(*row["b_static"]) == pytest.approx(B0)
            assert math.cos(heading(row) - (theta0 + turn * s.side * math.pi / 2)) == pytest.approx(1.0)
        # the pause before it: the aligning field alone, at the segment's heading (past the first pause's ramp)
        for row in before[pause // 2:]:
            assert row["segment"] == -1 and row["b_osc"] == 0 and row["freq"] == 0
            assert np.allclose(row["b_static"], drive[0]["b_static"])
    # after the last segment: coils off and CONVERGED
    end = sweep[block.total_frames]
    assert end["status"] == Status.CONVERGED and np.all(end["b_static"] == 0) and end["segment"] == -1
    assert all(row["status"] == Status.RUNNING for row in sweep[: block.total_frames])


def test_the_first_pause_turns_the_field_from_the_robots_heading_never_by_180_degrees(block, sweep):
    hold, pause = _frames(E.hold), _frames(E.pause)
    ramp = sweep[hold: hold + pause]
    headings = np.unwrap([math.atan2(r["b_static"][1], r["b_static"][0]) for r in ramp])
    # the robot heads +x (heading_est 0), θ0 = π: the field starts within a step of the robot's heading ...
    steps = np.abs(np.diff(np.concatenate([[0.0], headings])))
    assert steps.max() <= math.pi / max(1, pause // 2) + 1e-9
    # ... and reaches θ0 halfway through the pause
    assert math.cos(headings[pause // 2] - math.pi) == pytest.approx(1.0)


def test_theta0_points_away_from_the_nearest_sphere_and_the_square_turns_away_from_the_others():
    robot = np.array([2.4e-3, 1.8e-3])
    near = robot + np.array([0.0, 1.0e-3])           # nearest, straight "up": θ0 points down
    other = robot + np.array([1.2e-3, -0.4e-3])      # to the right: the square must go left (clockwise from -y)
    theta0, turn = square_start(robot, [other, near], E.side_max, COMMON.clearance, COMMON.field_margin)
    assert math.cos(theta0 + math.pi / 2) == pytest.approx(1.0)
    assert turn == -1.0                              # θ0 - 90° from -y is -x
    mirrored = [2 * robot[0] - other[0], other[1]]   # the same, to the left: the square goes right
    theta0, turn = square_start(robot, [mirrored, near], E.side_max, COMMON.clearance, COMMON.field_margin)
    assert turn == 1.0
    # the default scene: squares from the robot stay the field margin inside the field and the clearance off the sphere
    theta0, turn = square_start(ROBOT, [SPHERE], E.side_max, COMMON.clearance, COMMON.field_margin)
    u0 = np.array([math.cos(theta0), math.sin(theta0)])
    u1 = np.array([math.cos(theta0 + turn * math.pi / 2), math.sin(theta0 + turn * math.pi / 2)])
    corners = ROBOT + E.side_max * np.array([u0, u0 + u1, u1])
    assert inside_field(corners, COMMON.field_margin).all()
    assert np.hypot(*(corners - SPHERE).T).min() >= COMMON.clearance


@pytest.mark.parametrize("where", ["sphere", "edge"])
def test_a_sphere_within_the_clearance_or_the_field_edge_stops_the_sweep(block, where):
    segs = block.segments()
    k_stop = segs[2].start + 2  # while driving
    if where == "sphere":
        bad = _obs(spheres=[ROBOT + np.array([0.0, 0.99 * COMMON.clearance])])
    else:
        bad = _obs(robot=[0.99 * COMMON.field_margin, H / 2], spheres=[[3.0e-3, 1.8e-3]])
    rows = _run(block, k_stop + 5, at=lambda k: bad if k >= k_stop else _obs())
    assert all(r["status"] == Status.RUNNING for r in rows[:k_stop])
    assert rows[k_stop - 1]["b_osc"] > 0
    for r in rows[k_stop:]:  # latched: coils off, STALLED, even when the estimate comes back
        assert r["status"] == Status.STALLED and np.all(r["b_static"] == 0) and r["b_osc"] == 0 and r["freq"] == 0
        assert r["segment"] == -1
    # just outside the clearance and the margin the sweep goes on
    margin, clearance = COMMON.field_margin, COMMON.clearance
    ok = _obs(robot=[1.01 * margin, H / 2], spheres=[[1.01 * margin, H / 2 + 1.01 * clearance]])
    assert all(r["status"] == Status.RUNNING for r in _run(block, k_stop + 2, ok))


def test_lost_frames_zero_the_field_and_too_many_stop_the_sweep(block):
    segs = block.segments()
    k0 = segs[1].start + 1
    n_lost = int(E.max_lost)

    def lost_at(first, count):
        return lambda k: _obs(lost=first <= k < first + count)

    rows = _run(block, k0 + n_lost + 4, at=lost_at(k0, n_lost))  # as many as tolerated: zeroed, then on
    for r in rows[k0: k0 + n_lost]:
        assert r["status"] == Status.RUNNING and np.all(r["b_static"] == 0) and r["b_osc"] == 0
        assert r["segment"] == -1
    assert rows[k0 + n_lost]["segment"] == segs[1].index and rows[k0 + n_lost]["b_osc"] == segs[1].b_osc
    rows = _run(block, k0 + n_lost + 4, at=lost_at(k0, n_lost + 10))
    assert rows[k0 + n_lost]["status"] == Status.TRACKING_LOST
    assert all(r["status"] == Status.TRACKING_LOST and r["b_osc"] == 0 for r in rows[k0 + n_lost:])


def test_settings_are_validated_and_overridable():
    p = ExcitationParams.resolve(hold=0.5, side_max=300e-6)
    assert p.hold == 0.5 and p.side_max == 300e-6 and p.pause == E.pause
    b = Excitation("task", n_spheres=0, params=p)
    assert b.segments()[0].start == _frames(0.5) + _frames(E.pause)
    assert max(s.speed * s.frames * DT for s in b.segments()) <= 300e-6 * (1 + 1e-12)
    for bad in ({"hold": -1.0}, {"segment": 0.0}, {"side_max": float("nan")}, {"frequencies": []},
                {"min_segment": 10.0}, {"max_lost_frames": 1.5}):
        with pytest.raises(MagctlError):
            ExcitationParams.resolve(**bad)
    with pytest.raises(MagctlError, match="no cell"):
        Excitation("task", params=ExcitationParams.resolve(side_max=1e-9, amplitudes=[max(E.b_osc)]))
