"""Coil geometry from ``models/coils.toml`` and the field it makes, computed with magpylib.

A coil is a winding of ``N`` turns with mean radius ``a``, axial length ``l``
and radial depth ``d``; it is represented by a grid of circular filaments
spread over that cross-section, each carrying ``N/n`` of the ampere-turns.
With ``l = d = 0`` it is a single filament of ``N`` turns, whose field on its
axis is the textbook closed form ``B_z = µ0 N I a² / (2 (a² + z²)^{3/2})``.

The actuation matrix ``A`` maps the six coil currents to the field quantities
the actuator controls at the workspace centre,
``[B_x, B_y, B_z, ∂B_z/∂z] = A · i``; fields superpose linearly in the
currents, so one magpylib evaluation per coil at unit current gives ``A``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from magpylib.func import circle_field
from scipy.spatial.transform import Rotation

from magctl.config import Params, load_model
from magctl.core.batched import rows_times
from magctl.core.errors import ParameterError

COIL_KEYS = ("position", "axis", "turns", "radius", "length", "depth", "resistance", "inductance",
             "current_limit", "voltage_limit")
FILAMENTS_PER_SIDE = 3
"""Filament grid per coil cross-section (3 × 3); finer grids change B at the centre by < 0.1 %."""


@dataclass(frozen=True)
class Coil:
    """One electromagnet: geometry (m, unit axis) and electrical data (Ω, H, A, V).

    Attributes
    ----------
    name : str
        Table name in the model file (``xp``, ``xn``, …).
    position : ndarray (3,)
        Centre of the winding, m.
    axis : ndarray (3,)
        Unit vector along the coil axis; positive current makes field along it.
    turns : float
        Number of turns ``N``.
    radius, length, depth : float
        Mean winding radius ``a``, axial length and radial depth of the winding, m.
    resistance, inductance : float
        ``R`` (Ω) and ``L`` (H) of the winding.
    current_limit, voltage_limit : float
        Amplifier limits ``|i| ≤ I_max`` (A) and ``|v| ≤ V_max`` (V).
    """

    name: str
    position: np.ndarray
    axis: np.ndarray
    turns: float
    radius: float
    length: float
    depth: float
    resistance: float
    inductance: float
    current_limit: float
    voltage_limit: float

    @property
    def time_constant(self) -> float:
        """``τ = L / R``, s."""
        return self.inductance / self.resistance

    def filaments(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Filament centres (n, 3), diameters (n,) and turns per filament (n,)."""
        n = FILAMENTS_PER_SIDE
        offs = (np.arange(n) + 0.5) / n - 0.5
        z_off = offs * self.length if self.length > 0 else np.zeros(1)
        r_off = offs * self.depth if self.depth > 0 else np.zeros(1)
        zz, rr = np.meshgrid(z_off, r_off, indexing="ij")
        centres = self.position + zz.reshape(-1, 1) * self.axis
        diameters = 2.0 * (self.radius + rr.reshape(-1))
        turns = np.full(diameters.shape, self.turns / diameters.size)
        return centres, diameters, turns

    def rotation(self) -> Rotation:
        """Rotation taking the loop's local z axis onto :attr:`axis`."""
        ez = np.array([0.0, 0.0, 1.0])
        cross = np.cross(ez, self.axis)
        s, c = np.linalg.norm(cross), float(ez @ self.axis)
        if s < 1e-12:
            return Rotation.identity() if c > 0 else Rotation.from_rotvec([np.pi, 0.0, 0.0])
        return Rotation.from_rotvec(cross / s * np.arctan2(s, c))


def coil_from_params(name: str, p: Params, where: str) -> Coil:
    """Build a :class:`Coil` from its table, checking every value; errors name the file and key."""
    missing = [k for k in COIL_KEYS if k not in p]
    if missing:
        raise ParameterError(f"{where}: coil {name!r} is missing {missing}")

    def vec(key):
        v = np.asarray(p[key], dtype=float)
        if v.shape != (3,):
            raise ParameterError(f"{where}: coil {name!r} key {key!r} must be 3 numbers, got {p.raw.get(key)!r}")
        return v

    pos, axis = vec("position"), vec("axis")
    norm = np.linalg.norm(axis)
    if not norm > 0:
        raise ParameterError(f"{where}: coil {name!r} key 'axis' must be a non-zero vector")
    scalars = {k: p[k] for k in COIL_KEYS[2:]}
    for k, v in scalars.items():
        if np.ndim(v) != 0:
            raise ParameterError(f"{where}: coil {name!r} key {k!r} must be a single number")
        positive = k not in ("length", "depth")
        if (positive and not v > 0) or v < 0:
            raise ParameterError(f"{where}: coil {name!r} key {k!r} = {v!r} must be "
                                 f"{'positive' if positive else 'non-negative'}")
    return Coil(name=name, position=pos, axis=axis / norm, **{k: float(v) for k, v in scalars.items()})


@dataclass(frozen=True)
class CoilSet:
    """The six coils and the actuation settings of ``models/coils.toml``.

    Attributes
    ----------
    coils : tuple of Coil
        In file order.
    centre : ndarray (3,)
        Workspace centre where the actuation matrix is evaluated, m.
    waveform : str
        Oscillation waveform; ``"sine"`` (see docs/plant-actuator.md).
    clamp_gradient : float
        Commanded ``∂B_z/∂z`` at the centre, T/m (0: no clamping).
    source : str
        File the set was read from.
    """

    coils: tuple[Coil, ...]
    centre: np.ndarray
    waveform: str
    clamp_gradient: float
    source: str

    @property
    def resistance(self) -> np.ndarray:
        return np.array([c.resistance for c in self.coils])

    @property
    def inductance(self) -> np.ndarray:
        return np.array([c.inductance for c in self.coils])

    @property
    def current_limit(self) -> np.ndarray:
        return np.array([c.current_limit for c in self.coils])

    @property
    def voltage_limit(self) -> np.ndarray:
        return np.array([c.voltage_limit for c in self.coils])

    def field(self, points, currents) -> np.ndarray:
        """Total field ``B`` (T) at ``points`` (P, 3) m for coil ``currents`` (6,) A: (P, 3)."""
        points = np.atleast_2d(np.asarray(points, dtype=float))
        currents = np.asarray(currents, dtype=float)
        if currents.shape != (len(self.coils),):
            raise ValueError(f"currents must have shape ({len(self.coils)},), got {currents.shape}")
        per_coil = self.unit_fields(points)  # (6, P, 3)
        return np.einsum("c,cpk->pk", currents, per_coil)

    def unit_fields(self, points) -> np.ndarray:
        """Field of each coil at 1 A, shaped (6, P, 3), T/A."""
        points = np.atleast_2d(np.asarray(points, dtype=float))
        out = np.empty((len(self.coils), len(points), 3))
        for c, coil in enumerate(self.coils):
            centres, diam, turns = coil.filaments()
            nf, npt = len(diam), len(points)
            b = circle_field(
                "B",
                observers=np.tile(points, (nf, 1)),
                diameters=np.repeat(diam, npt),
                currents=np.repeat(turns, npt),
                positions=np.repeat(centres, npt, axis=0),
                orientations=Rotation.concatenate([coil.rotation()] * (nf * npt)),
                squeeze=False,
            )
            out[c] = b.reshape(nf, npt, 3).sum(axis=0)
        return out

    def allocation(self) -> CoilAllocation:
        """The minimum-norm allocation of :meth:`actuation_matrix` at the centre, with this set's clamp."""
        return CoilAllocation(np.linalg.pinv(self.actuation_matrix()), self.clamp_gradient)

    def actuation_matrix(self, point=None, h: float = 1e-4) -> np.ndarray:
        """``A`` (4, 6): rows ``B_x, B_y, B_z`` (T/A) and ``∂B_z/∂z`` (T/(m·A)) at ``point``.

        The gradient is a central difference over ``±h`` (m); the field varies on the
        scale of the coil radius (centimetres), so ``h = 0.1 mm`` is well resolved.
        """
        p = self.centre if point is None else np.asarray(point, dtype=float)
        pts = np.stack([p, p + [0.0, 0.0, h], p - [0.0, 0.0, h]])
        u = self.unit_fields(pts)  # (6, 3, 3)
        grad = (u[:, 1, 2] - u[:, 2, 2]) / (2.0 * h)
        return np.vstack([u[:, 0, :].T, grad[None, :]])


class CoilAllocation:
    """Field command → coil currents: the minimum-norm allocation ``i = A⁺ b`` (docs/plant-actuator.md).

    The static command is ``b = [b_x, b_y, 0, G_clamp]`` and the oscillation ``[0, 0, b_osc, 0]``; ``A``
    (4 × 6) is :meth:`CoilSet.actuation_matrix`. The one place where magctl turns a field into currents:
    the coil actuator block steps with it and the rig checks commands against coil ratings with it.

    Parameters
    ----------
    pinv : (n, 4) array
        ``A⁺``, A per (T, T, T, T/m).
    clamp_gradient : float
        ``G_clamp`` of the static command, T/m.
    """

    def __init__(self, pinv, clamp_gradient: float = 0.0):
        self.pinv = np.asarray(pinv, dtype=float)
        if self.pinv.ndim != 2 or self.pinv.shape[1] != 4:
            raise ParameterError(f"coil allocation needs an (n, 4) pseudo-inverse, got shape {self.pinv.shape}")
        self.clamp_gradient = float(clamp_gradient)
        self.clamp_currents = self.clamp_gradient * self.pinv[:, 3]
        """Static currents of the clamp term ``G_clamp·A⁺[:, 3]`` (n,), A."""
        self.per_tesla_xy = np.ascontiguousarray(self.pinv[:, :2].T)
        """(2, n): A per T of ``b_x``, ``b_y``."""
        self.per_tesla_osc = np.abs(self.pinv[:, 2])
        """(n,): current amplitude per T of oscillation."""

    def static_currents(self, b_static: np.ndarray) -> np.ndarray:
        """Signed static currents ``(B, n)`` A for ``b_static`` ``(B, 2)`` T (row by row, batch-safe)."""
        return rows_times(b_static, self.per_tesla_xy) + self.clamp_currents

    def osc_currents(self, b_osc: np.ndarray) -> np.ndarray:
        """Current amplitudes ``(B, n)`` A of the oscillation ``b_osc`` ``(B,)`` T."""
        return np.abs(b_osc)[:, None] * self.per_tesla_osc


def load_coils(name: str = "coils") -> CoilSet:
    """Read ``models/<name>.toml`` into a :class:`CoilSet`; a malformed file raises ParameterError."""
    p = load_model(name)
    where = p._path
    if "coil" not in p or not isinstance(p.coil, Params):
        raise ParameterError(f"{where}: needs a [coil.<name>] table per coil")
    coils = tuple(coil_from_params(n, p.coil[n], where) for n in p.coil)
    if len(coils) != 6:
        raise ParameterError(f"{where}: [coil.*] must define 6 coils, found {len(coils)}")
    if "actuation" not in p:
        raise ParameterError(f"{where}: missing [actuation] table")
    act = p.actuation
    for key in ("centre", "waveform", "clamp_gradient"):
        if key not in act:
            raise ParameterError(f"{where}: [actuation] is missing {key!r}")
    if act.waveform != "sine":
        raise ParameterError(f"{where}: [actuation] waveform {act.waveform!r} not supported (use \"sine\")")
    centre = np.asarray(act.centre, dtype=float)
    if centre.shape != (3,):
        raise ParameterError(f"{where}: [actuation] centre must be 3 numbers")
    return CoilSet(coils, centre, act.waveform, float(act.clamp_gradient), where)
