"""The paper's measured and fitted numbers the plant is judged against (§IV-D, Fig 6, eq 22-23).

The plant has one sphere (ε = 25 nm, the measured roughness) and no per-study parameter; these are
the observables it must predict: D_p,r (127 µm simulated, 300 ± 75 µm measured) and the side-push
curve of eq 22 / eq 23 at :data:`FIG6_GAPS` (docs/fluid.md §7-8).
"""

from __future__ import annotations

import numpy as np

PAPER_RELEASE_EXPERIMENT = 300e-6
"""D_p,r measured in the paper (§IV-D: 300 ± 75 µm over five trials)."""
PAPER_RELEASE_SIMULATION = 127e-6
"""D_p,r of the paper's COMSOL/ode23s simulation (§IV-D)."""
EQ22_A, EQ22_B = 1755e-6, 0.009042e6
"""eq 22 fit of the paper's simulated Fig 6: D_s = a exp(-b D_g), a [m], b [1/m]."""
FIG6_GAPS = np.array([370e-6, 450e-6, 500e-6, 550e-6, 600e-6, 650e-6])
"""Side gaps at which the plant's Fig 6 is judged against eq 22 (the paper's 370 µm bound to its 650 µm plot edge)."""


def eq22(gaps):
    """The paper's simulated side-push curve, eq 22 inverted: D_s = 1755 µm · exp(-0.009042/µm · D_g)."""
    return EQ22_A * np.exp(-EQ22_B * np.asarray(gaps, float))


def eq23_gap(ds):
    """eq 23: D_g = -5.29 D_s + 621 µm (inputs and outputs in metres)."""
    return -5.29 * np.asarray(ds, float) + 621e-6
