"""The README's first results, as a new user meets them: every command of "A first result in seconds" and the block
example, on a fresh clone with empty compile caches (installation excluded).

The repository at HEAD is cloned into a temporary folder; each step runs as its own process with the clone first on
``PYTHONPATH`` (so magctl, its ``models/`` and ``analysis/`` come from the clone) and ``NUMBA_CACHE_DIR`` pointing at
an empty folder, as on a machine that has never compiled magctl's kernels. The commands are read from the README
itself (the first fenced block under "A first result in seconds", and the Python block after it), so the benchmark
times what the page says.

Target: the whole first-result path under a minute.
"""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from rows import fmt, row

ROOT = Path(__file__).resolve().parents[1]
TARGET_S = 60.0


def readme_first_steps(text: str) -> tuple[list[list[str]], str]:
    """The commands of the README's "A first result in seconds" section and its Python example."""
    section = text.split("## A first result in seconds", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```(\w*)\n(.*?)```", section, flags=re.S)
    commands = [shlex.split(line.split("#", 1)[0]) for lang, body in blocks if lang == ""
                for line in body.splitlines() if line.strip().startswith("magctl ")]
    python = next(body for lang, body in blocks if lang == "python")
    return commands, python


def run(quick: bool = False) -> dict:
    commands, python = readme_first_steps((ROOT / "README.md").read_text())
    steps = []
    with tempfile.TemporaryDirectory() as tmp:
        clone, cache = Path(tmp) / "magctl", Path(tmp) / "numba-cache"
        subprocess.run(["git", "clone", "-q", str(ROOT), str(clone)], check=True)
        env = {**os.environ, "PYTHONPATH": str(clone), "NUMBA_CACHE_DIR": str(cache)}
        env.pop("MAGCTL_MODELS", None)
        env.pop("MAGCTL_STUDIES", None)
        for argv in [*commands, ["python", "-c", python]]:
            cmd = [sys.executable, "-m", *argv] if argv[0] == "magctl" else [sys.executable, *argv[1:]]
            t0 = time.perf_counter()
            proc = subprocess.run(cmd, cwd=clone, env=env, capture_output=True, text=True)
            wall = time.perf_counter() - t0
            if proc.returncode != 0:
                raise RuntimeError(f"{' '.join(argv[:3])}: exit {proc.returncode}: {proc.stderr.strip()[-300:]}")
            steps.append({"step": " ".join(argv) if argv[0] == "magctl" else "the README's Python example",
                          "wall_s": wall})
    total = sum(s["wall_s"] for s in steps)
    slowest = max(steps, key=lambda s: s["wall_s"])
    return {"steps": steps, "total_s": total, "rows": [
        row("README: a first result, fresh clone, empty compile caches (install excluded)", total, "s", le=TARGET_S,
            note=f"{len(steps)} steps: " + "; ".join(f"{s['step'].removeprefix('magctl ')} {fmt(s['wall_s'])} s"
                                                     for s in steps) + f"; slowest: {slowest['step']}")],
        "all_met": total <= TARGET_S}


if __name__ == "__main__":
    import json

    print(json.dumps(run(), indent=2))
