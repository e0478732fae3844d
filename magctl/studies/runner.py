"""Studies: one file each in ``analysis/``, run by ``magctl study NAME`` and ``magctl reproduce``.

A study is three steps, so that its numbers can be computed (and tested) without
matplotlib, and its figures redrawn without recomputing::

    NAME = "sidepush-curve"          # the command-line name
    TITLE = "Fig 6 — side-push displacement versus gap"
    ORDER = 30                       # position in the report (smaller first)
    DEFAULT_TRIALS = 100             # optional; trials when --trials is not given
    REUSES = ("front-push",)         # optional; studies whose trials this one may reuse
    REPRODUCE = False                # optional; leave it out of ``magctl reproduce`` (minutes of
                                     # flow solves on a cold cache); ``magctl study NAME`` runs it

    def compute(ctx: StudyContext) -> Computed: ...
        # every simulation and reduction; never imports matplotlib
    def draw(computed: Computed, ctx: StudyContext) -> list[Path]: ...
        # every figure (matplotlib imported inside), written with ctx.figure_path
    def summarise(computed: Computed) -> tuple[list[str], list[PaperRow]]: ...
        # the report's Markdown lines and its paper-vs-magctl rows

:func:`run_study` composes the three into a :class:`StudyResult`.

Trials shared between studies go through the context's :class:`TrialCache`, one per
``magctl reproduce`` run (a fresh one for ``magctl study NAME``). A study sees only the
entries it stored itself or that a study named in its ``REUSES`` stored; it says in its
summary which trials it reused, and computes them itself when run alone.

``analysis/`` is not a top-level package in site-packages: a checkout reads the folder at
the top of the repository, an installed wheel the copy it carries as package data
(``magctl/_data/analysis``); ``$MAGCTL_STUDIES`` points at another folder.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import os
import sys
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Any

from magctl.core.errors import MagctlError
from magctl.studies.paper_statistics import Cause, verdict  # the studies import Cause from here, with claim

STEPS = ("compute", "draw", "summarise")
"""The functions every study module defines."""


MODELS = ("closed loop", "attempt map", "analysis", "fluid model")
"""What can produce a row's magctl number: the 30 Hz closed-loop simulation, the attempt-to-attempt
map (eq 14–18 iterated), a closed-form or linear analysis, or the fluid model on its own."""
VERDICTS = ("reproduced", "consistent at n = 10", "not resolvable", "not reproduced", "opposite")
"""The verdicts of :data:`magctl.studies.paper_statistics.RULE`."""


@dataclass
class PaperRow:
    """One line of the report's paper-vs-magctl tables.

    A row with a ``verdict`` is a claim of the paper (its §VI when ``section`` says so): it goes
    into the claim-by-claim table, and a verdict other than "reproduced" must name its ``cause``
    in one sentence.

    Attributes
    ----------
    quantity : str
        The claim or quantity.
    paper, magctl : str
        The paper's value or statement, and magctl's.
    note : str
        Anything else the reader needs (plant, trials).
    model : str
        Which of :data:`MODELS` produced magctl's number.
    verdict : str
        One of :data:`VERDICTS`, or empty for a plain comparison.
    cause : str
        Why the claim is not reproduced (required then).
    section : str
        The paper's section of the claim, e.g. "§VI-A".
    p_paper : float or None
        Probability of the paper's observation (at its ten trials) under magctl's model
        (:mod:`magctl.studies.paper_statistics`); None where the claim is not a ten-trial observation.
    """

    quantity: str
    paper: str
    magctl: str
    note: str = ""
    model: str = ""
    verdict: str = ""
    cause: str = ""
    section: str = ""
    p_paper: float | None = None

    def __post_init__(self):
        if self.model and self.model not in MODELS:
            raise MagctlError(f"paper row {self.quantity!r}: model {self.model!r} is not one of {', '.join(MODELS)}")
        if self.verdict and self.verdict not in VERDICTS:
            raise MagctlError(f"paper row {self.quantity!r}: verdict {self.verdict!r} is not one of "
                              f"{', '.join(VERDICTS)}")
        if self.verdict and self.verdict != "reproduced" and not self.cause:
            raise MagctlError(f"paper row {self.quantity!r}: verdict {self.verdict!r} needs its cause")
        if self.verdict == "reproduced":
            self.cause = ""


def claim(section: str, quantity: str, paper: str, magctl: str, model: str, *, holds: bool,
          cause: Cause, opposite: bool = False, note: str = "", p_paper: float | None = None,
          ordering: bool = False) -> PaperRow:
    """A claim of the paper with its verdict by :func:`magctl.studies.paper_statistics.verdict`: reproduced when
    ``holds``; otherwise judged by ``p_paper``, the probability of the paper's ten-trial observation under
    magctl's model (``ordering``: the claim ranks two controllers), with its computed ``cause``."""
    if not isinstance(cause, Cause):
        raise MagctlError(f"paper claim {quantity!r}: the cause must be a computed Cause, got {type(cause).__name__}")
    v = verdict(holds, p_paper, ordering=ordering, opposite=opposite)
    return PaperRow(quantity, paper, magctl, note=note, model=model, verdict=v, cause=cause.text(), section=section,
                    p_paper=p_paper)


@dataclass
class Computed:
    """What a study's ``compute`` step returns.

    Attributes
    ----------
    results : dict
        Plain JSON-able numbers with unit-suffixed keys (µm, s): what ``results.json`` and
        ``magctl study NAME --json`` carry.
    data : dict
        Whatever else the figures and the summary need (curves, trajectories, SI values);
        not written out.
    """

    results: dict[str, Any]
    data: dict[str, Any] = field(default_factory=dict)


@dataclass
class StudyResult:
    """What :func:`run_study` returns.

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


class TrialCache:
    """Trial results shared between the studies of one run, each entry held under the study that stored it.

    Keys are whatever identifies a batch of trials completely (for push trials: the
    experiment, the number of trials and the root seed; the executor does not enter,
    since a trial's result does not depend on it). A study looks entries up through
    :meth:`lookup` with the studies it may take them from, so reuse happens only where a
    study declares it (``REUSES``). Two studies that store the same key keep one entry
    each: neither overwrites the other's.
    """

    def __init__(self) -> None:
        self._entries: dict[tuple[str, str], Any] = {}

    def __len__(self) -> int:
        return len(self._entries)

    def __contains__(self, key: str) -> bool:
        return any(k == key for _, k in self._entries)

    def store(self, key: str, producer: str, value: Any) -> None:
        """Keep ``value`` under ``key``, stored by study ``producer``."""
        self._entries[(producer, key)] = value

    def lookup(self, key: str, allowed: Iterable[str]) -> tuple[str, Any] | None:
        """``(producer, value)`` for the first of the ``allowed`` studies that stored ``key``, else None."""
        for producer in allowed:
            if (producer, key) in self._entries:
                return producer, self._entries[(producer, key)]
        return None


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
    fem : bool
        Also run the finite-element models (minutes; ``magctl study … --fem``, needs the ``fem`` extra).
    trial_cache : TrialCache
        Trials shared between the studies of one run; ``magctl reproduce`` hands every
        study the same one.
    study : str
        The study running in this context (set by :func:`run_study`).
    reuses : tuple of str
        Studies whose cached trials this one may use (its ``REUSES``, set by :func:`run_study`).
    conditions : str
        ``"magctl"`` or ``"paper"``: the conditions its closed-loop controllers run under
        (:mod:`magctl.studies.conditions`).
    """

    out: Path
    trials: int | None = None
    seed: int = 0
    scheduler: str | None = None
    workers: int | None = None
    quiet: bool = False
    fem: bool = False
    trial_cache: TrialCache = field(default_factory=TrialCache)
    study: str = ""
    reuses: tuple[str, ...] = ()
    conditions: str = "magctl"

    def n_trials(self, default: int) -> int:
        """Trials to run: ``--trials`` if given, else the study's ``default``."""
        return int(self.trials) if self.trials is not None else int(default)

    def progress(self, iterable: Iterable, desc: str, total: int | None = None):
        """Wrap ``iterable`` in a progress bar on stderr unless quiet or not a terminal."""
        from magctl.core.progress import progress

        return progress(iterable, desc=desc, total=total, quiet=self.quiet)

    def figure_path(self, stem: str, suffix: str = ".png") -> Path:
        """``out/stem.suffix``, creating ``out``."""
        self.out.mkdir(parents=True, exist_ok=True)
        return self.out / f"{stem}{suffix}"


def studies_dir() -> Path:
    """The folder of study modules: ``$MAGCTL_STUDIES`` or the shipped ``analysis/`` (see ``config.data_dir``)."""
    from magctl.config import data_dir

    env = os.environ.get("MAGCTL_STUDIES")
    return Path(env) if env else data_dir("analysis")


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
    """Every study in ``analysis/``, keyed by NAME, in report order.

    A module counts as a study when it defines ``NAME``; it must then define
    ``compute``, ``draw`` and ``summarise``.
    """
    folder = studies_dir()
    if not folder.is_dir():
        raise MagctlError(f"study folder {folder} not found (set MAGCTL_STUDIES)")
    found = {}
    for path in sorted(folder.glob("*.py")):
        if path.name.startswith("_"):
            continue
        module = _load(path)
        name = getattr(module, "NAME", None)
        if name is None:
            continue
        missing = [step for step in STEPS if not callable(getattr(module, step, None))]
        if missing:
            raise MagctlError(f"study {name!r} ({path.name}) does not define {', '.join(missing)}")
        found[name] = module
    if not found:
        raise MagctlError(f"study folder {folder} holds no studies (modules defining NAME, compute, draw and "
                          "summarise); point MAGCTL_STUDIES at a folder of studies, or unset it for the shipped ones")
    return dict(sorted(found.items(), key=lambda kv: (getattr(kv[1], "ORDER", 100), kv[0])))


def reproduced(studies: dict[str, ModuleType]) -> dict[str, ModuleType]:
    """The studies ``magctl reproduce`` runs by default: all but those with ``REPRODUCE = False``."""
    return {name: m for name, m in studies.items() if getattr(m, "REPRODUCE", True)}


def check_reuses(studies: dict[str, ModuleType]) -> None:
    """Check that every ``REUSES`` names a study that comes earlier in ``studies`` (report order).

    Raises
    ------
    MagctlError
        A study reuses one that does not exist, or one that would run after it, so its
        trials could never be there to reuse.
    """
    order = list(studies)
    for name, module in studies.items():
        for other in getattr(module, "REUSES", ()):
            if other not in studies:
                raise MagctlError(f"study {name!r} reuses trials of {other!r}, which is not a study")
            if order.index(other) > order.index(name):
                raise MagctlError(f"study {name!r} reuses trials of {other!r}, which runs after it "
                                  f"(ORDER {getattr(studies[other], 'ORDER', 100)} > "
                                  f"{getattr(module, 'ORDER', 100)})")


def get(name: str) -> ModuleType:
    """The study module called ``name``."""
    studies = discover()
    try:
        return studies[name]
    except KeyError:
        raise MagctlError(f"no study {name!r}; studies: {', '.join(studies) or 'none'}") from None


def compute(name: str, ctx: StudyContext) -> Computed:
    """Run study ``name``'s compute step only (no figures, no matplotlib).

    Parameters
    ----------
    name : str
        Study name (its ``NAME``).
    ctx : StudyContext
        Passed on with ``study`` set to ``name`` and ``reuses`` to the module's ``REUSES``;
        the trial cache is the same object.

    Returns
    -------
    Computed

    Raises
    ------
    MagctlError
        No such study, or its compute step returned something else than :class:`Computed`.
    """
    module = get(name)
    ctx = dataclasses.replace(ctx, study=name, reuses=tuple(getattr(module, "REUSES", ())))
    computed = module.compute(ctx)
    if not isinstance(computed, Computed):
        raise MagctlError(f"study {name!r} compute returned {type(computed).__name__}, not Computed")
    return computed


def run_study(name: str, ctx: StudyContext, *, figures: bool = True) -> StudyResult:
    """Compute study ``name``, draw its figures and summarise it.

    Parameters
    ----------
    name : str
        Study name.
    ctx : StudyContext
    figures : bool
        False: no ``draw`` step (no files written, matplotlib not needed).

    Returns
    -------
    StudyResult
        ``results`` from compute, ``figures`` from draw, ``summary`` and ``paper`` from summarise.
    """
    module = get(name)
    computed = compute(name, ctx)
    paths = list(module.draw(computed, ctx)) if figures else []
    summary, paper = module.summarise(computed)
    return StudyResult(name, computed.results, paths, list(summary), list(paper))
