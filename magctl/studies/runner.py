"""Studies: one file each in ``analysis/``, run by ``magctl study NAME`` and ``magctl reproduce``.

A study module defines::

    NAME = "sidepush-curve"          # the command-line name
    TITLE = "Fig 6 — side-push displacement versus gap"
    ORDER = 30                       # position in the report (smaller first)
    DEFAULT_TRIALS = 100             # optional; trials when --trials is not given

    def run(ctx: StudyContext) -> StudyResult: ...

``analysis/`` is not installed into site-packages; it is found beside the
package (or at ``$MAGCTL_STUDIES``).
"""

from __future__ import annotations

import importlib.util
import os
import sys
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Any

from magctl.core.errors import MagctlError


@dataclass
class PaperRow:
    """One line of the report's "paper vs magctl" table."""

    quantity: str
    paper: str
    magctl: str
    note: str = ""


@dataclass
class StudyResult:
    """What a study returns.

    Attributes
    ----------
    name : str
        Study name.
    results : dict
        Plain JSON-able numbers with unit-suffixed keys (µm, s).
    figures : list of Path
        PNG (and GIF) files written into the study's output folder.
    summary : list of str
        Markdown lines for the report and the readable console summary.
    paper : list of PaperRow
        Rows for the paper-vs-magctl table.
    """

    name: str
    results: dict[str, Any]
    figures: list[Path] = field(default_factory=list)
    summary: list[str] = field(default_factory=list)
    paper: list[PaperRow] = field(default_factory=list)


@dataclass
class StudyContext:
    """Everything a study needs from the command line.

    Attributes
    ----------
    out : Path
        Folder for the study's figures (created).
    trials : int or None
        Trials requested with ``--trials``; None means the study's default.
    seed : int
        Root seed of every random stream.
    scheduler : str or None
        Dask scheduler address for sweeps (``--scheduler``); None = local processes.
    workers : int or None
        Local worker processes (default: CPU count).
    quiet : bool
        No progress output.
    """

    out: Path
    trials: int | None = None
    seed: int = 0
    scheduler: str | None = None
    workers: int | None = None
    quiet: bool = False

    def n_trials(self, default: int) -> int:
        return int(self.trials) if self.trials is not None else int(default)

    def progress(self, iterable: Iterable, desc: str, total: int | None = None):
        """Wrap ``iterable`` in a progress bar on stderr unless quiet or not a terminal."""
        from magctl.core.progress import progress

        return progress(iterable, desc=desc, total=total, quiet=self.quiet)

    def figure_path(self, stem: str, suffix: str = ".png") -> Path:
        self.out.mkdir(parents=True, exist_ok=True)
        return self.out / f"{stem}{suffix}"


def studies_dir() -> Path:
    env = os.environ.get("MAGCTL_STUDIES")
    return Path(env) if env else Path(__file__).resolve().parents[2] / "analysis"


def _load(path: Path) -> ModuleType:
    mod_name = f"magctl_study_{path.stem}"
    if mod_name in sys.modules:
        return sys.modules[mod_name]
    spec = importlib.util.spec_from_file_location(mod_name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[mod_name] = module
    spec.loader.exec_module(module)
    return module


def discover() -> dict[str, ModuleType]:
    """Every study in ``analysis/``, keyed by NAME, in report order."""
    folder = studies_dir()
    if not folder.is_dir():
        raise MagctlError(f"study folder {folder} not found (set MAGCTL_STUDIES)")
    found = {}
    for path in sorted(folder.glob("*.py")):
        if path.name.startswith("_"):
            continue
        module = _load(path)
        name = getattr(module, "NAME", None)
        if name is None or not callable(getattr(module, "run", None)):
            continue
        found[name] = module
    return dict(sorted(found.items(), key=lambda kv: (getattr(kv[1], "ORDER", 100), kv[0])))


def get(name: str) -> ModuleType:
    studies = discover()
    try:
        return studies[name]
    except KeyError:
        raise MagctlError(f"no study {name!r}; studies: {', '.join(studies) or 'none'}") from None


def run_study(name: str, ctx: StudyContext) -> StudyResult:
    module = get(name)
    result = module.run(ctx)
    if not isinstance(result, StudyResult):
        raise MagctlError(f"study {name!r} returned {type(result).__name__}, not a StudyResult")
    return result
