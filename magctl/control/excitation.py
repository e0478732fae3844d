"""The open-loop excitation of ``magctl rig run --task identify``: a speed sweep for identification.

The schedule (times in frames of ``dt``, values from ``models/identify.toml`` ``[experiment]``)::

    hold  (coils off: b_static = 0, b_osc = 0, f = 0)                                   hold_s
    for each cell (f, b_osc) of frequencies × b_osc (frequency major), kept if its segment ≥ min_segment_s:
        for side j = 0 … 3, heading θ_j = θ₀ + σ·j·90°:
            pause   aligning field only: b_static = B₀ (cos θ_j, sin θ_j), b_osc = 0, f = 0   pause_s
            drive   b_static as above, b_osc, f                                             T_c
    done (coils off, status CONVERGED)

``B₀`` is the drive's aligning field (``models/robot.toml`` ``[drive] static_field_mT``), so the robot turns in
place during a pause and translates along ``θ_j`` during a drive. A cell's drive lasts

    T_c = min(segment_s, side_max / v(B₀, b_osc, f))          (whole frames, rounded down)

with ``v`` the model's steady stick-slip speed (:func:`magctl.plant.robot.steady_speed`, default robot), so that the
predicted side of each square is at most ``side_max``; the four sides are equal, and the robot returns near its
start after every cell. A cell with ``T_c < min_segment_s`` is left out (its speed could not be measured).

``θ₀`` points from the nearest sphere to the robot (first frame's estimates), and the turn sign ``σ = ±1`` puts
the square on the side that keeps it farther from the spheres and the field's edges. During the first pause the
field direction turns from the robot's first heading estimate to ``θ₀`` over half the pause, so that the robot is
never asked to turn by exactly 180° (an unstable equilibrium of the aligning torque).

Outputs besides the command: ``status`` (:class:`~magctl.control.status.Status`) and ``segment``: the index
``4·c + j`` into :meth:`Excitation.segments` while driving side ``j`` of kept cell ``c``, ``-1`` in the hold, the
pauses, lost frames and after the end, so that run logs can be cut into segments.

Safety (every frame, from the estimates): a robot within ``clearance`` of a sphere or outside the camera field
shrunk by ``field_margin`` (:func:`magctl.sensing.camera.field_of_view`) zeroes the command and ends the sweep with
``STALLED``; a lost frame zeroes the command (the schedule's clock runs on) and more than ``max_lost_frames`` lost
frames in a row end it with ``TRACKING_LOST``. An end is latched: the command stays zero.

The block is a Python block (no kernel): it is one table lookup per frame, and the rig's
:class:`~magctl.rig.tasks.Controller` runs a diagram with a Python block interpreted.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from magctl import FRAME_PERIOD_S
from magctl.config import load_model
from magctl.core.block import Block, StateVar
from magctl.core.errors import MagctlError
from magctl.core.ports import DIMENSIONLESS, Port
from magctl.plant.drive import load_drive
from magctl.plant.robot import StickSlipParams, load_robot, steady_speed
from magctl.sensing.camera import field_of_view, outside_view

from .status import Status

__all__ = ["Excitation", "ExcitationParams", "Segment", "inside_field", "square_start"]

HOLD, PAUSE, DRIVE, DONE = 0, 1, 2, 3
"""Phases of the schedule (per frame)."""
QUARTER = 0.5 * math.pi


@dataclass(frozen=True)
class ExcitationParams:
    """The sweep's settings (SI), ``models/identify.toml`` ``[experiment]`` and the drive's aligning field.

    Attributes
    ----------
    hold, pause, segment, min_segment : float
        Coils-off hold at the start, aligning-only pause before each segment, longest and shortest drive
        segment, s.
    side_max : float
        Largest predicted side of a square, m.
    clearance, field_margin : float
        The sweep stops when the robot comes nearer a sphere than ``clearance`` or nearer the camera field's
        edge than ``field_margin``, m.
    frequencies, amplitudes : tuple of float
        The grid: field frequencies, 1/s, and rocking amplitudes ``b_osc``, T.
    static_field : float
        ``B₀``, the aligning field, T (``models/robot.toml`` ``[drive]``).
    max_lost_frames : int
        Lost frames in a row tolerated (with the field off) before the sweep stops.
    """

    hold: float
    pause: float
    segment: float
    min_segment: float
    side_max: float
    clearance: float
    field_margin: float
    frequencies: tuple[float, ...]
    amplitudes: tuple[float, ...]
    static_field: float
    max_lost_frames: int

    OPTIONS = ("hold", "pause", "segment", "side_max", "clearance")
    """The settings a rig run may override (``magctl rig run --task identify --option hold_s=5``)."""

    @classmethod
    def resolve(cls, **given) -> ExcitationParams:
        """The settings with ``given`` (a keyword left ``None`` takes the file's value), validated."""
        unknown = sorted(set(given) - set(cls.__dataclass_fields__))
        if unknown:
            raise MagctlError(f"identify: unknown setting(s) {', '.join(unknown)}")
        e, common = load_model("identify").experiment, load_model("push").common
        defaults = {"hold": e.hold, "pause": e.pause, "segment": e.segment, "min_segment": e.min_segment,
                    "side_max": e.side_max, "clearance": common.clearance, "field_margin": common.field_margin,
                    "frequencies": e.frequencies, "amplitudes": e.b_osc, "static_field": load_drive().static_field,
                    "max_lost_frames": e.max_lost}
        values = {k: defaults[k] if given.get(k) is None else given[k] for k in defaults}
        return cls._checked(values)

    @classmethod
    def _checked(cls, v: dict) -> ExcitationParams:
        def bad(name, want):
            return MagctlError(f"identify: {name}={v[name]!r} must be {want}")

        for name in ("hold", "pause", "clearance", "field_margin"):
            if not (_number(v[name]) and v[name] >= 0):
                raise bad(name, "a finite number ≥ 0")
        for name in ("segment", "min_segment", "side_max", "static_field"):
            if not (_number(v[name]) and v[name] > 0):
                raise bad(name, "a finite number > 0")
        if v["min_segment"] > v["segment"]:
            raise MagctlError(f"identify: min_segment={v['min_segment']!r} s exceeds segment={v['segment']!r} s")
        for name in ("frequencies", "amplitudes"):
            arr = np.atleast_1d(np.asarray(v[name], dtype=float))
            if arr.ndim != 1 or arr.size == 0 or not np.all(np.isfinite(arr)) or not np.all(arr > 0):
                raise bad(name, "a non-empty list of finite numbers > 0")
            v[name] = tuple(float(x) for x in arr)
        lost = v["max_lost_frames"]
        if isinstance(lost, bool) or not _number(lost) or lost < 0 or float(lost) != int(lost):
            raise bad("max_lost_frames", "a whole number ≥ 0")
        v["max_lost_frames"] = int(lost)
        return cls(**{k: (float(x) if k in ("hold", "pause", "segment", "min_segment", "side_max", "clearance",
                                            "field_margin", "static_field") else x) for k, x in v.items()})


def _number(x) -> bool:
    try:
        return math.isfinite(float(x))
    except (TypeError, ValueError):
        return False


@dataclass(frozen=True)
class Segment:
    """One drive segment of the sweep: side ``side`` of cell ``cell``.

    Attributes
    ----------
    index : int
        The ``segment`` output while it drives (``4·cell + side``).
    freq, b_osc : float
        The command's frequency (1/s) and rocking amplitude (T).
    cell, side : int
        Kept cell (frequency major) and side of its square (0-3; heading ``θ₀ + σ·side·90°``).
    start, frames : int
        First frame of the drive (frames since the sweep's first frame) and its length.
    speed : float
        The model's steady speed for the command, m/s; ``speed · frames · dt ≤ side_max``.
    """

    index: int
    freq: float
    b_osc: float
    cell: int
    side: int
    start: int
    frames: int
    speed: float


def inside_field(points, margin: float, span: tuple[float, float] | None = None) -> np.ndarray:
    """Which of ``points`` ``(..., 2)`` [m] lie at least ``margin`` inside the camera's field of view."""
    w, h = span if span is not None else field_of_view()
    p = np.asarray(points, dtype=float)
    return ~outside_view(p - margin, (w - 2.0 * margin, h - 2.0 * margin))


def square_start(robot, spheres, side: float, clearance: float, margin: float,
                 span: tuple[float, float] | None = None) -> tuple[float, float]:
    """``(θ₀, σ)``: the first heading and the turn sign of a square of side ``side`` driven from ``robot``.

    ``θ₀`` points away from the nearest sphere (the direction from it to the robot); without a (finite) sphere
    it is the axis direction that keeps the square farthest inside the field. ``σ`` (``+1`` counter-clockwise)
    is the side that keeps the square's path farther from every sphere (beyond ``clearance``) and from the
    field's edges (beyond ``margin``); ties go to ``+1``.
    """
    span = span if span is not None else field_of_view()
    robot = np.asarray(robot, dtype=float).reshape(2)
    sph = np.asarray(spheres, dtype=float).reshape(-1, 2)
    sph = sph[np.all(np.isfinite(sph), axis=1)]
    if len(sph):
        d = robot - sph[np.argmin(np.hypot(*(sph - robot).T))]
        headings = [math.atan2(d[1], d[0]) if np.any(d != 0) else 0.0]
    else:
        headings = [k * QUARTER for k in range(4)]
    best, choice = -np.inf, (headings[0], 1.0)
    for th in headings:
        for turn in (1.0, -1.0):
            room = _square_room(robot, sph, th, turn, side, clearance, margin, span)
            if room > best:
                best, choice = room, (float(th), turn)
    return choice


def _square_room(robot, spheres, theta0, turn, side, clearance, margin, span) -> float:
    """The least slack of the square's path: distance beyond ``clearance`` to a sphere, beyond ``margin`` to an edge."""
    u0 = np.array([math.cos(theta0), math.sin(theta0)])
    u1 = np.array([math.cos(theta0 + turn * QUARTER), math.sin(theta0 + turn * QUARTER)])
    corners = robot + side * np.array([[0.0, 0.0], u0, u0 + u1, u1, [0.0, 0.0]])
    s = np.linspace(0.0, 1.0, 9)[:, None, None]
    path = (corners[:-1] + s * (corners[1:] - corners[:-1])).reshape(-1, 2)
    w, h = span
    room = float(np.min(np.minimum(np.minimum(path[:, 0], w - path[:, 0]), np.minimum(path[:, 1], h - path[:, 1]))
                        - margin))
    if len(spheres):
        dist = np.hypot(*(path[:, None, :] - spheres[None, :, :]).transpose(2, 0, 1))
        room = min(room, float(dist.min() - clearance))
    return room


class Excitation(Block):
    """The open-loop speed sweep of the ``identify`` task (module docstring: schedule, safety, outputs).

    Ports: inputs ``robot_est`` (2,) m, ``heading_est`` () rad, ``spheres_est`` (N, 2) m, ``lost`` () bool;
    outputs ``b_static`` (2,) T, ``b_osc`` () T, ``freq`` () 1/s, ``status`` () int64, ``segment`` () int64.

    Parameters
    ----------
    name : str
    n_spheres : int
        ``N``, the width of ``spheres_est``.
    params : ExcitationParams, optional
        ``ExcitationParams.resolve()`` (``models/identify.toml``) when omitted.
    robot : StickSlipParams, optional
        The model predicting each cell's speed (``models/robot.toml``).
    span : (float, float), optional
        The camera's field of view ``(w, h)``, m (``models/camera.toml``).
    dt : float
        Frame period, s.
    """

    def __init__(self, name: str = "task", *, n_spheres: int = 1, params: ExcitationParams | None = None,
                 robot: StickSlipParams | None = None, span: tuple[float, float] | None = None,
                 dt: float = FRAME_PERIOD_S):
        self.params = p = ExcitationParams.resolve() if params is None else params
        self.robot = load_robot() if robot is None else robot
        self.span = tuple(float(x) for x in (span if span is not None else field_of_view()))
        n = int(n_spheres)
        super().__init__(name, inputs=[Port("robot_est", (2,), "m"), Port("heading_est", (), "rad"),
                                       Port("spheres_est", (n, 2), "m"), Port("lost", (), DIMENSIONLESS, "bool")],
                         outputs=[Port("b_static", (2,), "T"), Port("b_osc", (), "T"), Port("freq", (), "1/s"),
                                  Port("status", (), DIMENSIONLESS, "int64"),
                                  Port("segment", (), DIMENSIONLESS, "int64")],
                         dt=dt, feedthrough=True)
        self.hold_frames = _frames(p.hold, dt)
        self.pause_frames = _frames(p.pause, dt)
        self.ramp_frames = max(1, self.pause_frames // 2)
        self._segments = self._schedule()
        if not self._segments:
            raise MagctlError(f"identify: no cell of the grid drives for min_segment={p.min_segment:g} s within "
                              f"side_max={p.side_max * 1e6:g} µm")
        self._tables()

    # --- the schedule ------------------------------------------------------------------------------------------
    def _schedule(self) -> list[Segment]:
        p, dt = self.params, self.dt
        most, least = _frames(p.segment, dt), _frames(p.min_segment, dt)
        out: list[Segment] = []
        k = self.hold_frames
        cell = 0
        for f in p.frequencies:
            for b in p.amplitudes:
                v = float(steady_speed(self.robot, p.static_field, b, f))
                frames = most if v <= 0 else min(most, int(math.floor(p.side_max / (v * dt))))
                if frames < max(least, 1):
                    continue
                for j in range(4):
                    k += self.pause_frames
                    out.append(Segment(4 * cell + j, float(f), float(b), cell, j, k, frames, v))
                    k += frames
                cell += 1
        return out

    def _tables(self) -> None:
        """Per-frame lookup tables, frame ``total_frames`` being the end."""
        total = self._segments[-1].start + self._segments[-1].frames
        n = total + 1
        self._phase = np.full(n, PAUSE, dtype=np.int64)
        self._phase[: self.hold_frames] = HOLD
        self._phase[total] = DONE
        self._side = np.zeros(n, dtype=np.int64)        # quarter turns since θ₀ (0-3)
        self._seg = np.full(n, -1, dtype=np.int64)
        self._freq = np.zeros(n)
        self._bosc = np.zeros(n)
        for s in self._segments:
            self._side[s.start - self.pause_frames: s.start + s.frames] = s.side
            sl = slice(s.start, s.start + s.frames)
            self._phase[sl], self._seg[sl], self._freq[sl], self._bosc[sl] = DRIVE, s.index, s.freq, s.b_osc
        self.total_frames = total

    def segments(self) -> list[Segment]:
        """The drive segments in order; ``segments()[i].index == i``."""
        return list(self._segments)

    @property
    def duration(self) -> float:
        """The sweep's length, s (``total_frames · dt``)."""
        return self.total_frames * self.dt

    # --- the block ----------------------------------------------------------------------------------------------
    def state_vars(self):
        return (StateVar("k", (), "int64", "k", "frames since the sweep's first frame"),
                StateVar("theta0", (), symbol="θ₀", description="heading of each square's first side, rad"),
                StateVar("turn", (), symbol="σ", description="turn sign of the squares (+1 counter-clockwise)"),
                StateVar("psi0", (), symbol="ψ₀", description="the robot's heading estimate at the first frame, rad"),
                StateVar("lost_frames", (), "int64", description="lost frames in a row"),
                StateVar("end", (), "int64", description="the status that ended the sweep (0 while it runs)"))

    def initial_state(self, batch, rng=None):
        return {"k": np.zeros(batch, dtype=np.int64), "theta0": np.zeros(batch), "turn": np.ones(batch),
                "psi0": np.zeros(batch), "lost_frames": np.zeros(batch, dtype=np.int64),
                "end": np.zeros(batch, dtype=np.int64)}

    def step(self, state, u):
        """The command at frame ``k`` and the next state (the first frame latches ``θ₀``, ``σ`` and ``ψ₀``)."""
        p = self.params
        k = state["k"]
        robot, spheres = np.asarray(u["robot_est"], float), np.asarray(u["spheres_est"], float)
        lost = np.asarray(u["lost"], bool) | ~np.all(np.isfinite(robot), axis=1)
        theta0, turn, psi0 = state["theta0"].copy(), state["turn"].copy(), state["psi0"].copy()
        for b in np.flatnonzero(k == 0):
            theta0[b], turn[b] = square_start(robot[b], spheres[b], p.side_max, p.clearance, p.field_margin,
                                              self.span)
            psi0[b] = float(u["heading_est"][b])
        idx = np.minimum(k, self.total_frames)
        phase = self._phase[idx]
        lost_frames = np.where(lost, state["lost_frames"] + 1, 0)
        end = state["end"].copy()
        running = (end == 0) & (phase != DONE)
        too_close = self._unsafe(robot, spheres)
        end = np.where(running & lost & (lost_frames > p.max_lost_frames), int(Status.TRACKING_LOST), end)
        end = np.where((end == 0) & running & ~lost & too_close, int(Status.STALLED), end)
        end = np.where((end == 0) & (phase == DONE), int(Status.CONVERGED), end)
        on = (end == 0) & ~lost & (phase != HOLD)
        drive = on & (phase == DRIVE)

        heading = theta0 + turn * QUARTER * self._side[idx]
        first = (idx >= self.hold_frames) & (idx < self.hold_frames + self.pause_frames) & np.isfinite(psi0)
        if np.any(first):   # the first pause turns the field from ψ₀ to θ₀ the short way (never by exactly 180°)
            frac = np.minimum(1.0, (idx - self.hold_frames + 1) / self.ramp_frames)
            heading = np.where(first, psi0 + _wrap(theta0 - psi0) * frac, heading)
        b0 = np.where(on, p.static_field, 0.0)
        out = {"b_static": np.stack([b0 * np.cos(heading), b0 * np.sin(heading)], axis=1),
               "b_osc": np.where(drive, self._bosc[idx], 0.0), "freq": np.where(drive, self._freq[idx], 0.0),
               "status": end.astype(np.int64), "segment": np.where(drive, self._seg[idx], -1).astype(np.int64)}
        nxt = {"k": k + 1, "theta0": theta0, "turn": turn, "psi0": psi0, "lost_frames": lost_frames.astype(np.int64),
               "end": end.astype(np.int64)}
        return out, nxt

    def _unsafe(self, robot: np.ndarray, spheres: np.ndarray) -> np.ndarray:
        p = self.params
        out = ~inside_field(robot, p.field_margin, self.span)
        if spheres.shape[1]:
            dist = np.hypot(*(spheres - robot[:, None, :]).transpose(2, 0, 1))
            out |= np.any(np.isfinite(dist) & (dist < p.clearance), axis=1)
        return out

    def output(self, state, u):
        return self.step(state, u)[0]

    def update(self, state, u):
        return self.step(state, u)[1]


def _frames(seconds: float, dt: float) -> int:
    """Whole frames in ``seconds`` (rounded to the nearest)."""
    return int(round(seconds / dt))


def _wrap(a):
    """Angles wrapped to ``[-π, π)``."""
    return (np.asarray(a) + math.pi) % (2.0 * math.pi) - math.pi
