"""magctl: modelling, analysis and control of magnetic micro-robot pushing rigs.

The package has three uses built from one set of blocks: stability and gain
analysis of the push loops, batched closed-loop simulation, and deployment on
a rig through a hardware adapter.
"""

__version__ = "0.2.0"

FRAME_RATE_HZ = 30.0
"""Camera frame rate; the base rate of every diagram (paper §II)."""

FRAME_PERIOD_S = 1.0 / FRAME_RATE_HZ
