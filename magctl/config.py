"""Typed parameters loaded and validated from ``models/*.toml``.

Every parameter in a model file carries its unit in its key and its source
next to its value::

    [sphere]
    radius_um = { value = 105, source = "paper §II: 210 µm diameter PS-DVB spheres" }
    density_kg_m3 = { value = 1050, source = "assumed: polystyrene handbook value" }

:func:`load_model` returns nested :class:`Params` whose attributes are in SI
with the unit suffix stripped (``sphere.radius`` is 1.05e-4 m). Keys without a
unit suffix that the table below does not know, values that are not numbers
(or lists of numbers, strings, booleans), and missing ``source`` entries are
errors naming the file and the key.

Files named in :data:`RULES` are also checked for type and range (positive rates, a watchdog
within sane bounds, finite positive ratings…), in the units written in the file; a value
outside its range is an error naming the file, the key and the allowed range.
"""

from __future__ import annotations

import fnmatch
import math
import os
import tomllib
from collections.abc import Iterator
from importlib import resources
from pathlib import Path
from typing import Any

from magctl.core.errors import ParameterError

# unit suffix → (SI unit, factor to SI)
UNITS: dict[str, tuple[str, float]] = {
    "m": ("m", 1.0), "mm": ("m", 1e-3), "um": ("m", 1e-6), "nm": ("m", 1e-9),
    "s": ("s", 1.0), "ms": ("s", 1e-3), "us": ("s", 1e-6),
    "Hz": ("1/s", 1.0), "per_s": ("1/s", 1.0), "per_s2": ("1/s^2", 1.0), "per_um": ("1/m", 1e6),
    "m_s": ("m/s", 1.0), "mm_s": ("m/s", 1e-3), "um_s": ("m/s", 1e-6),
    "rad": ("rad", 1.0), "deg": ("rad", math.pi / 180.0), "rad_s": ("rad/s", 1.0),
    "kg": ("kg", 1.0), "kg_m3": ("kg/m^3", 1.0), "g_cm3": ("kg/m^3", 1e3),
    "N": ("N", 1.0), "uN": ("N", 1e-6), "nN": ("N", 1e-9),
    "Pa_s": ("Pa*s", 1.0), "mPa_s": ("Pa*s", 1e-3), "cSt": ("m^2/s", 1e-6),
    "J_m2": ("J/m^2", 1.0), "mJ_m2": ("J/m^2", 1e-3),
    "T": ("T", 1.0), "mT": ("T", 1e-3), "T_m": ("T/m", 1.0), "mT_m": ("T/m", 1e-3),
    "A": ("A", 1.0), "V": ("V", 1.0), "ohm": ("ohm", 1.0), "H": ("H", 1.0), "mH": ("H", 1e-3),
    "A_m": ("A/m", 1.0), "kA_m": ("A/m", 1e3), "A_m2": ("A*m^2", 1.0), "N_m": ("N*m", 1.0),
    "pixels": ("1", 1.0), "frames": ("1", 1.0), "count": ("1", 1.0), "ratio": ("1", 1.0),
    "1": ("1", 1.0), "px": ("1", 1.0), "percent": ("1", 1e-2),
}
_SUFFIXES = sorted(UNITS, key=len, reverse=True)


def split_unit(key: str) -> tuple[str, str | None]:
    """``"radius_um"`` → ``("radius", "um")``; keys without a known suffix → ``(key, None)``."""
    for suf in _SUFFIXES:
        if key.endswith("_" + suf) and len(key) > len(suf) + 1:
            return key[: -len(suf) - 1], suf
    return key, None


class Params:
    """A table of parameters in SI; attribute and item access by the unit-less name.

    Attributes ``sources`` (name → source text) and ``units`` (name → SI unit)
    document every value. Sub-tables are nested ``Params``.
    """

    def __init__(self, path: str, values: dict[str, Any], sources: dict[str, str], units: dict[str, str],
                 raw: dict[str, Any]):
        self._path = path
        self._values = values
        self.sources = sources
        self.units = units
        self.raw = raw

    def __getattr__(self, name: str):
        if name.startswith("_"):
            raise AttributeError(name)
        try:
            return self._values[name]
        except KeyError:
            raise ParameterError(
                f"{self._path}: no parameter {name!r}; has {sorted(self._values)}"
            ) from None

    __getitem__ = __getattr__

    def __contains__(self, name: str) -> bool:
        return name in self._values

    def __iter__(self) -> Iterator[str]:
        return iter(self._values)

    def get(self, name: str, default=None):
        return self._values.get(name, default)

    def to_dict(self) -> dict[str, Any]:
        """Values as written in the file (unit-suffixed keys), for JSON and run logs."""
        return {k: (v.to_dict() if isinstance(v, Params) else v) for k, v in self.raw.items()}

    def __repr__(self) -> str:
        return f"<Params {self._path} {sorted(self._values)}>"


def _parse_table(where: str, table: dict[str, Any]) -> Params:
    values, sources, units, raw = {}, {}, {}, {}
    for key, entry in table.items():
        loc = f"{where}.{key}" if where.count(":") else f"{where}:{key}"
        if isinstance(entry, dict) and "value" not in entry:
            sub = _parse_table(loc, entry)
            values[key], raw[key] = sub, sub.to_dict()
            continue
        if not isinstance(entry, dict):
            raise ParameterError(f"{loc}: write parameters as {{ value = …, source = \"…\" }}, got {entry!r}")
        extra = set(entry) - {"value", "source", "note"}
        if extra:
            raise ParameterError(f"{loc}: unknown fields {sorted(extra)} (allowed: value, source, note)")
        source = entry.get("source")
        if not isinstance(source, str) or not source.strip():
            raise ParameterError(f"{loc}: missing 'source' (the paper with section, a datasheet, or 'assumed: why')")
        name, suffix = split_unit(key)
        value = entry["value"]
        if isinstance(value, (str, bool)) and suffix is not None:
            raise ParameterError(f"{loc}: value {value!r} is not a number, and the key's unit suffix _{suffix} "
                                 "says it is one")
        if isinstance(value, (str, bool)):
            values[name] = value
            units[name] = ""
        else:
            if suffix is None:
                raise ParameterError(
                    f"{loc}: numeric parameter needs a unit suffix in its key (e.g. _um, _s, _A, _1); "
                    f"known suffixes: {', '.join(sorted(UNITS))}"
                )
            import numpy as np  # here, so that reading the parameter layout does not need it

            try:
                arr = np.asarray(value, dtype=float)
            except (TypeError, ValueError):
                raise ParameterError(f"{loc}: value {value!r} is not a number or a list of numbers") from None
            if not np.all(np.isfinite(arr)):
                raise ParameterError(f"{loc}: value {value!r} is not finite")
            si_unit, factor = UNITS[suffix]
            values[name] = float(arr) * factor if arr.ndim == 0 else arr * factor
            units[name] = si_unit
        sources[name] = source
        raw[key] = value
    return Params(where, values, sources, units, raw)


# --- type and range rules -----------------------------------------------------------------------------
# file name → dotted key (fnmatch pattern) → (kind, low, high, required); bounds in the file's units, low
# exclusive when written as a 1-tuple: (0,) means "> 0". kind: number, integer, bool, str, numbers.
# (coils.toml is checked by its own loader, magctl.plant.coils.load_coils: positive finite ratings.)
_POS = (0,)
RULES: dict[str, dict[str, tuple]] = {
    "rig.toml": {
        "limits.b_static_max_mT": ("number", _POS, 100.0, True),
        "limits.b_osc_max_mT": ("number", _POS, 100.0, True),
        "limits.freq_max_Hz": ("number", _POS, 10000.0, True),
        "watchdog.timeout_ms": ("number", 10.0, 1000.0, True),
        "watchdog.lockstep_wall_timeout_ms": ("number", 10.0, 60000.0, False),
        "session.timeout_s": ("number", _POS, 3600.0, False),
        "session.takeover_interval_s": ("number", 0.0, 3600.0, False),
        "log.max_mb_1": ("number", 0.0, 1e6, False),
        "runtime.rate_Hz": ("number", _POS, 1000.0, True),
        "runtime.lost_timeout_s": ("number", _POS, 3600.0, True),
        "runtime.warn_interval_s": ("number", _POS, 3600.0, True),
        "runtime.spin_ms": ("number", 0.0, 100.0, True),
        "runtime.request_timeout_ms": ("number", 1.0, 60000.0, True),
        "runtime.configure_timeout_ms": ("number", 1.0, 600000.0, False),
        "scene.robot_start_um": ("numbers", -1e6, 1e6, False),
        "scene.sphere_spacing_um": ("number", _POS, 1e6, False),
        "physics.robot_steps": ("bool", None, None, False),
        "physics.camera_noise": ("bool", None, None, False),
        "physics.release_scatter_ratio": ("number", 0.0, 1.0, False),
        "standin.*_um": ("number", _POS, 1e6, False),
        "standin.*_mm": ("number", _POS, 1e4, False),
    },
    "camera.toml": {
        "camera.pixel_size_um": ("number", _POS, 1e3, True),
        "camera.width_px": ("integer", 1, 100000, True),
        "camera.height_px": ("integer", 1, 100000, True),
        "camera.latency_frames": ("integer", 0, 300, True),
        "camera.position_noise_px": ("number", 0.0, 1e3, True),
        "camera.heading_noise_deg": ("number", 0.0, 180.0, True),
        "camera.drop_probability_ratio": ("number", 0.0, 1.0, True),
        "tracker.max_coast_frames": ("integer", 0, 300, False),
        "tracker.particles_count": ("integer", 1, 10**6, False),
    },
}



def _flat(table: dict[str, Any], prefix: str = "") -> Iterator[tuple[str, Any]]:
    for key, entry in table.items():
        name = f"{prefix}{key}"
        if isinstance(entry, dict) and "value" not in entry:
            yield from _flat(entry, name + ".")
        elif isinstance(entry, dict):
            yield name, entry["value"]


def _range_text(lo, hi) -> str:
    left = f"> {lo[0]:g}" if isinstance(lo, tuple) else f">= {lo:g}"
    return f"{left} and <= {hi:g}"


def check_rules(path: Path, data: dict[str, Any]) -> None:
    """Type and range checks of :data:`RULES` for this file name; raises :class:`ParameterError`."""
    rules = RULES.get(path.name)
    if not rules:
        return
    values = dict(_flat(data))
    for pattern, (kind, lo, hi, required) in rules.items():
        keys = [k for k in values if fnmatch.fnmatchcase(k, pattern)]
        if required and not keys:
            raise ParameterError(f"{path}: missing parameter {pattern}")
        for key in keys:
            problem = _rule_problem(values[key], kind, lo, hi)
            if problem:
                raise ParameterError(f"{path}: {key} = {values[key]!r} {problem}")


def _rule_problem(v, kind, lo, hi) -> str | None:
    if kind == "bool":
        return None if isinstance(v, bool) else "must be true or false"
    if kind == "str":
        return None if isinstance(v, str) else "must be a string"
    items = v if kind == "numbers" else [v]
    if kind == "numbers" and not isinstance(v, list):
        return "must be a list of numbers"
    for x in items:
        if isinstance(x, bool) or not isinstance(x, (int, float)):
            return "must be a number" if kind != "integer" else "must be an integer"
        if kind == "integer" and not float(x).is_integer():
            return "must be an integer"
        if not math.isfinite(x):
            return "must be finite"
        low = lo[0] if isinstance(lo, tuple) else lo
        if (isinstance(lo, tuple) and not x > low) or (not isinstance(lo, tuple) and not x >= low) or not x <= hi:
            return f"is out of range (allowed: {_range_text(lo, hi)})"
    return None


def data_dir(kind: str) -> Path:
    """Where the shipped ``models/`` or ``analysis/`` folder is: the checkout's, else the installed package's.

    In a source checkout (``pyproject.toml`` beside the package) the folder at the top of the
    repository is used, so edits there take effect at once; an installed wheel carries the same
    files as package data (``magctl/_data/<kind>``, read through :mod:`importlib.resources`).
    """
    root = Path(__file__).resolve().parents[1]
    if (root / "pyproject.toml").is_file() and (root / kind).is_dir():
        return root / kind
    return Path(str(resources.files("magctl") / "_data" / kind))


def models_dir() -> Path:
    """The folder of parameter files: ``$MAGCTL_MODELS`` (a user's own set) or the shipped ``models/``."""
    env = os.environ.get("MAGCTL_MODELS")
    if env:
        return Path(env)
    return data_dir("models")


def model_versions(*names: str) -> tuple:
    """The parameter folder and each named file's modification time (-1: missing, the loaders name it): a cache
    key of what is read from those files, which changes when the folder is switched or a file is edited."""
    folder = models_dir()
    stamps = []
    for name in names:
        try:
            stamps.append(os.stat(folder / name).st_mtime_ns)
        except OSError:
            stamps.append(-1)
    return (str(folder), *stamps)


def read_toml(path: str | os.PathLike, what: str = "parameter file", error=ParameterError) -> dict:
    """The TOML document at ``path``; a missing, unreadable or malformed file raises ``error`` in one line naming
    the file (``what`` says which kind of file was expected)."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise error(f"{path}: {what} not found") from None
    except tomllib.TOMLDecodeError as err:
        raise error(f"{path}: not valid TOML: {err}") from None
    except UnicodeDecodeError as err:
        raise error(f"{path}: not UTF-8 text (byte {err.start})") from None
    except IsADirectoryError:
        raise error(f"{path}: is a directory, not a {what}") from None
    except OSError as err:
        raise error(f"{path}: cannot read: {err.strerror or err}") from None


def load_file(path: str | os.PathLike) -> Params:
    """Load and validate one TOML parameter file."""
    path = Path(path)
    data = read_toml(path)
    params = _parse_table(str(path), data)
    check_rules(path, data)
    return params


def parse_params(text: str, where: str) -> Params:
    """Parse and validate the text of one parameter file (a copy kept elsewhere, e.g. in a run log); ``where``
    names it in errors, and its file name picks the file's type rules as :func:`load_file` does."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ParameterError(f"{where}: not valid TOML: {err}") from None
    params = _parse_table(where, data)
    check_rules(Path(where), data)
    return params


def load_model(name: str) -> Params:
    """Load ``models/<name>.toml`` (e.g. ``load_model("sphere")``)."""
    return load_file(models_dir() / f"{name}.toml")


def require(params: Params, *names: str) -> None:
    """Raise a :class:`ParameterError` naming every missing parameter."""
    missing = [n for n in names if n not in params]
    if missing:
        raise ParameterError(f"{params._path}: missing parameters {missing}")
