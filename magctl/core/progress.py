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
