"""Write constraints.txt: the exact versions of magctl's run-time dependencies (and the view extra) that this
environment holds, their dependencies included — the versions the committed results were produced with.

    .venv/bin/python .ci/constraints.py        # after a `make demo` / `make test` install; commit the file

`make demo` and `make test` install with ``-c constraints.txt``, so a fresh clone reproduces with these versions.
"""

from __future__ import annotations

import sys
import tomllib
from importlib import metadata
from pathlib import Path

from packaging.requirements import Requirement

ROOT = Path(__file__).resolve().parents[1]
EXTRAS = ("view",)


def wanted() -> list[Requirement]:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    reqs = [Requirement(r) for r in project["dependencies"]]
    for extra in EXTRAS:
        reqs += [Requirement(r) for r in project["optional-dependencies"][extra]]
    return reqs


def closure(reqs: list[Requirement]) -> dict[str, str]:
    """Installed name → version of ``reqs`` and everything they require (markers evaluated here)."""
    seen: dict[str, str] = {}
    stack = list(reqs)
    while stack:
        req = stack.pop()
        key = req.name.lower().replace("_", "-")
        if key in seen:
            continue
        try:
            dist = metadata.distribution(req.name)
        except metadata.PackageNotFoundError:
            sys.exit(f"constraints: {req.name} is not installed here; install magctl[{','.join(EXTRAS)}] first")
        seen[key] = dist.version
        for text in dist.requires or []:
            sub = Requirement(text)
            if sub.marker is None or any(sub.marker.evaluate({"extra": e}) for e in ("", *req.extras)):
                stack.append(sub)
    return seen


def main() -> int:
    pins = closure(wanted())
    lines = ["# Exact versions of magctl's run-time dependencies and the view extra, their dependencies included:",
             "# the environment the committed results were produced in (written by .ci/constraints.py).",
             *(f"{name}=={version}" for name, version in sorted(pins.items()))]
    (ROOT / "constraints.txt").write_text("\n".join(lines) + "\n")
    print(f"constraints.txt: {len(pins)} pins", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
