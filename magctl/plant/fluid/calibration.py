"""The paper's measured and fitted numbers the plant is judged against (§IV-D, Fig 6, eq 22-23).

The plant has one sphere (ε = 25 nm, the measured roughness) and no per-study parameter; these are
the observables it must predict: D_p,r (127 µm simulated, 300 ± 75 µm measured) and the side-push
curve of eq 22 / eq 23 at :data:`FIG6_GAPS` (docs/fluid.md §7-8).
"""

from __future__ import annotations

import numpy as np

from magctl.config import load_model
from magctl.core.units import UM

PAPER_RELEASE_EXPERIMENT = 300e-6
"""D_p,r measured in the paper (§IV-D: 300 ± 75 µm over five trials)."""
PAPER_RELEASE_SIMULATION = 127e-6
"""D_p,r of the paper's COMSOL/ode23s simulation (§IV-D)."""
FIG6_GAPS = np.array([370e-6, 450e-6, 500e-6, 550e-6, 600e-6, 650e-6])
"""Side gaps at which the plant's Fig 6 is judged against eq 22 (the paper's 370 µm bound to its 650 µm plot edge)."""


def paper_side() -> dict[str, float]:
    """Eq 22's ``amplitude`` ``A`` (m) and ``rate`` ``k`` (1/m), eq 23's ``slope`` and ``intercept`` (m), as printed:
    ``models/push.toml`` ``[paper_side]``, converted from the file's µm as the constants were before they moved
    there (``A = 1755 * UM``, ``k = 0.009042 / UM``, …), so every model is the same double as it was."""
    raw = load_model("push").paper_side.raw
    return {"amplitude": raw["amplitude_um"] * UM, "rate": raw["rate_per_um"] / UM,
            "slope": float(raw["slope_1"]), "intercept": raw["intercept_um"] * UM}


def eq22(gaps):
    """The paper's simulated side-push curve, eq 22 inverted: D_s = A·exp(−k·D_g) (:func:`paper_side`: 1755 µm,
    0.009042 /µm)."""
    p = paper_side()
    return p["amplitude"] * np.exp(-p["rate"] * np.asarray(gaps, float))


def eq23_gap(ds):
    """eq 23: D_g = slope·D_s + intercept (:func:`paper_side`: −5.29, 621 µm; inputs and outputs in metres)."""
    p = paper_side()
    return p["slope"] * np.asarray(ds, float) + p["intercept"]
