"""Progress bars on stderr (tqdm), silent when asked or when stderr is not a terminal."""

from __future__ import annotations

import sys
from collections.abc import Iterable

from tqdm import tqdm


def progress(iterable: Iterable, desc: str, total: int | None = None, quiet: bool = False):
    """``iterable`` wrapped in a tqdm bar on stderr, or unchanged when silent."""
    if quiet or not sys.stderr.isatty():
        return iterable
    return tqdm(iterable, desc=desc, total=total, file=sys.stderr, leave=False)


class _Silent:
    """A counter that shows nothing."""

    def update(self, n: int = 1) -> None:
        pass

    def close(self) -> None:
        pass


def trial_counter(total: int, desc: str, quiet: bool = False):
    """A bar counting trials (``update(n)`` when a chunk of ``n`` trials is done), or a silent one.

    Shown on stderr only when it is a terminal and not ``quiet``; otherwise long work reports one
    line per study (the command line prints it), not a line per chunk.
    """
    if quiet or not sys.stderr.isatty():
        return _Silent()
    return tqdm(total=total, desc=desc, unit="trial", file=sys.stderr, leave=False)
