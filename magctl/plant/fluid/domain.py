"""What bounds the oil around the robot: the domain of the robot's Stokes flow.

The glass at ``z = 0`` is always a no-slip wall. Above it the oil is

``unbounded``
    a half-space (Blake's image system alone);
``lid``
    a layer of depth ``H`` under a no-slip plane at ``z = H`` (a cover slip);
``free_surface``
    a layer of depth ``H`` with a flat stress-free top (an open bath): zero normal
    velocity and zero shear stress at ``z = H``;
``box``
    the paper's COMSOL model (§IV-C): a finite box of ``length × 2·half_width × H``
    around the robot with inlet and outlet faces, a moving ground, symmetry
    (slip) faces elsewhere and a half model — solved by finite elements.

The domain is a rig parameter read from ``models/fluid.toml [domain]``; flows are
cached by :meth:`Domain.key`, so a changed domain never reuses a stale map.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from magctl.config import load_model
from magctl.core.errors import ParameterError

KINDS = ("unbounded", "lid", "free_surface", "box")


@dataclass(frozen=True)
class Domain:
    """The oil's bounds (lengths in metres).

    Attributes
    ----------
    kind : {"unbounded", "lid", "free_surface", "box"}
    depth : float
        H, height of the lid, the free surface or the box top above the glass [m]
        (``inf`` for ``unbounded``).
    box_length : float
        Box length along the robot's travel [m] (``box`` only).
    box_half_width : float
        Box half-width across the travel [m] (``box`` only; the half model spans ``0 ≤ y ≤ half_width``).
    """

    kind: str = "unbounded"
    depth: float = math.inf
    box_length: float = math.inf
    box_half_width: float = math.inf

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ParameterError(f"fluid domain kind must be one of {', '.join(KINDS)}, got {self.kind!r}")
        if self.kind == "unbounded":
            return
        if not (math.isfinite(self.depth) and self.depth > 0):
            raise ParameterError(f"fluid domain {self.kind!r} needs a finite positive depth, got {self.depth!r} m")
        if self.kind == "box":
            for name in ("box_length", "box_half_width"):
                v = getattr(self, name)
                if not (math.isfinite(v) and v > 0):
                    raise ParameterError(f"fluid domain 'box' needs a finite positive {name}, got {v!r} m")

    @property
    def bounded(self) -> bool:
        """Whether anything but the glass bounds the oil."""
        return self.kind != "unbounded"

    def key(self) -> tuple:
        """A hashable identity for flow caches."""
        if self.kind == "unbounded":
            return ("unbounded",)
        if self.kind == "box":
            return (self.kind, round(self.depth, 12), round(self.box_length, 12), round(self.box_half_width, 12))
        return (self.kind, round(self.depth, 12))

    def label(self) -> str:
        """Short human label, lengths in mm."""
        if self.kind == "unbounded":
            return "unbounded half-space"
        name = {"lid": "lid", "free_surface": "free surface", "box": "COMSOL box"}[self.kind]
        text = f"{name}, H = {self.depth * 1e3:g} mm"
        if self.kind == "box":
            text += f", {self.box_length * 1e3:g} × {2 * self.box_half_width * 1e3:g} mm"
        return text

    @classmethod
    def from_params(cls, fluid=None) -> Domain:
        """The domain of ``models/fluid.toml [domain]``."""
        p = fluid if fluid is not None else load_model("fluid")
        if "domain" not in p:
            return cls()
        d = p.domain
        kind = str(d.kind)
        if kind == "unbounded":
            return cls()
        return cls(kind, float(d.depth), float(d.get("box_length", math.inf)), float(d.get("box_half_width", math.inf)))
