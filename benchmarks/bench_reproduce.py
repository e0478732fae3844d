"""``magctl reproduce`` end to end, as ``make demo`` runs it: its default trials, 2 cores.

Targets (issue "one implementation per block"): ≤ 60 s with a warm compile cache. The compile-cache-cold
figure is measured too — the same command in a fresh process with empty caches (numba's and the generated
sources'), as on a machine that has never run magctl — and reported beside it. Each run's per-study wall
times come from its own ``timings.json``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from rows import row

TARGET_WARM_S = 60.0


def _reproduce(out: Path, env: dict, quick: bool) -> dict:
    cmd = [sys.executable, "-m", "magctl", "reproduce", "--out", str(out), "--quiet"]
    if quick:
        cmd += ["--trials", "5", "--no-figures"]
    t0 = time.perf_counter()
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    if done.returncode:
        return {"error": (done.stderr.strip().splitlines() or ["failed"])[-1], "wall_s": wall}
    timings = json.loads((out / "timings.json").read_text())["wall_time_s"]
    return {"wall_s": wall, "studies_s": timings}


def run(quick: bool = False) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        cold_env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp / "numba"), MAGCTL_CACHE=str(tmp / "magctl"))
        cold = _reproduce(tmp / "cold", cold_env, quick)
        warm = _reproduce(tmp / "warm", cold_env, quick)      # the same caches, now filled
    out = {"quick": quick, "target_warm_s": TARGET_WARM_S, "cold": cold, "warm": warm}
    out["rows"] = [row("magctl reproduce, default trials, 2 cores, warm compile cache", warm["wall_s"], "s",
                       le=TARGET_WARM_S, note=f"compile cache cold: {cold['wall_s']:.0f} s"
                       + (" (quick run: --trials 5, no figures)" if quick else ""))]
    return out


if __name__ == "__main__":
    print(json.dumps(run(quick="--quick" in sys.argv), indent=2, default=float))
