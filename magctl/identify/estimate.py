"""One identified parameter: its value and uncertainty, where it goes in the parameter folder, and its source."""

from __future__ import annotations

from dataclasses import dataclass

from magctl.core.errors import MagctlError


class IdentifyError(MagctlError):
    """The logs cannot be used for identification (wrong format, torn, mixed rigs …)."""


class NotIdentified(MagctlError):
    """A parameter the given logs do not determine; the reason says what the logs lack."""


@dataclass(frozen=True)
class Estimate:
    """An identified parameter.

    Attributes
    ----------
    file, table, key : str
        Where it is written: ``models/<file>``, table ``[table]``, key as written there, unit suffix included
        (``"camera.toml"``, ``"camera"``, ``"latency_frames"``).
    value, uncertainty : float
        The estimate and its standard uncertainty (1σ), in the unit of ``key``'s suffix.
    evidence : str
        What it was fitted to and how well: "from 412 stationary frames of run.jsonl, ML fit …".
    """

    file: str
    table: str
    key: str
    value: float
    uncertainty: float
    evidence: str

    @property
    def name(self) -> str:
        """``file:table.key``, e.g. ``camera.toml:camera.latency_frames``."""
        return f"{self.file}:{self.table}.{self.key}"

    def source(self) -> str:
        """The ``source`` text the parameter folder records."""
        return f"identified: {self.value:.6g} ± {self.uncertainty:.2g} (1σ) {self.evidence}"
