"""The identification tests start real ``serve-sim`` servers with the rig tests' helper."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "rig"))
