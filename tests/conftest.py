"""Suite-wide settings.

Property-based tests draw their examples from a fixed seed so that a CI run and a
local run explore the same cases; set HYPOTHESIS_PROFILE=explore to search afresh.
"""

import os

from hypothesis import settings

settings.register_profile("ci", derandomize=True)
settings.register_profile("explore", derandomize=False)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))
