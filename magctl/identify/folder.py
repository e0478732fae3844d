"""Write an identified parameter folder: a copy of the parameter files with the identified values in place.

Every file of the base folder (``$MAGCTL_MODELS`` or the shipped ``models/``) is copied line for line; the line of
each identified key gets the new value and a ``source`` that says "identified:", the value's uncertainty, the
logs and frames it came from and the fit's quality (:meth:`Estimate.source`). Values the logs did not determine
keep their line, so their source still says where the default came from; ``identified.json`` lists both, with
the reason each value was not identified. The folder is loaded back before it is reported written, so a folder
``magctl identify`` writes is one ``--models DIR`` accepts.
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Iterable
from pathlib import Path

from magctl.config import load_file, models_dir
from magctl.identify.estimate import Estimate, IdentifyError

_TABLE = re.compile(r"^\s*\[([A-Za-z0-9_.-]+)\]\s*(#.*)?$")


def _toml_string(text: str) -> str:
    return json.dumps(text, ensure_ascii=False)


def _format_value(value: float, old: str) -> str:
    """``value`` written as the old value was: an integer stays an integer."""
    if re.fullmatch(r"-?\d+", old.strip()):
        return str(int(round(value)))
    return repr(float(value))


def replace_value(text: str, table: str, key: str, value: float, source: str, path: str = "") -> str:
    """``text`` (a parameter file) with ``[table] key``'s value and source replaced; an error if it has no such key."""
    lines = text.split("\n")
    current = None
    pattern = re.compile(rf"^(\s*{re.escape(key)}\s*=\s*\{{\s*value\s*=\s*)([^,]+?)"
                         r"(\s*,\s*source\s*=\s*)(\".*\")(\s*\}.*)$")
    for i, line in enumerate(lines):
        m = _TABLE.match(line)
        if m:
            current = m.group(1)
            continue
        if current != table:
            continue
        m = pattern.match(line)
        if m:
            lines[i] = f"{m.group(1)}{_format_value(value, m.group(2))}{m.group(3)}{_toml_string(source)}{m.group(5)}"
            return "\n".join(lines)
    raise IdentifyError(f"{path or 'parameter file'}: no [{table}] {key} to write the identified value to")


def write_folder(out: Path, estimates: Iterable[Estimate], not_identified: dict[str, str], logs: list[str],
                 base: Path | None = None) -> Path:
    """Write the parameter folder ``out`` (created; existing parameter files in it are an error) from ``base``
    with ``estimates`` in place, plus ``identified.json``; returns ``out``."""
    base = Path(base) if base is not None else models_dir()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    clash = sorted(p.name for p in out.glob("*.toml"))
    if clash:
        raise IdentifyError(f"{out}: already holds parameter files ({', '.join(clash[:3])}…); give an empty folder")
    texts = {p.name: p.read_text(encoding="utf-8") for p in sorted(base.glob("*.toml"))}
    estimates = list(estimates)
    for e in estimates:
        if e.file not in texts:
            raise IdentifyError(f"{base}: has no {e.file} to write {e.name} to")
        texts[e.file] = replace_value(texts[e.file], e.table, e.key, e.value, e.source(), e.file)
    for name, text in texts.items():
        (out / name).write_text(text, encoding="utf-8")
    for name in texts:        # the folder must load: a bad value is this module's error, not the next command's
        load_file(out / name)
    record = {"logs": logs, "base": str(base),
              "identified": [{"parameter": e.name, "value": e.value, "uncertainty": e.uncertainty,
                              "evidence": e.evidence} for e in estimates],
              "not_identified": not_identified}
    tmp = out / "identified.json.tmp"
    tmp.write_text(json.dumps(record, indent=1, ensure_ascii=False) + "\n", encoding="utf-8")
    os.replace(tmp, out / "identified.json")
    return out


def copy_with(out: Path, values: dict[tuple[str, str, str], float], why: str, base: Path | None = None) -> Path:
    """A parameter folder ``out`` copied from ``base`` with ``values`` ({(file, table, key): value}) in place, each
    with the source ``why`` — a rig to simulate whose parameters differ from the model's (the identification's
    round trip), or a what-if study. Loaded back before it is returned."""
    base = Path(base) if base is not None else models_dir()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    texts = {p.name: p.read_text(encoding="utf-8") for p in sorted(base.glob("*.toml"))}
    for (file, table, key), value in values.items():
        if file not in texts:
            raise IdentifyError(f"{base}: has no {file} to set [{table}] {key} in")
        texts[file] = replace_value(texts[file], table, key, value, why, file)
    for name, text in texts.items():
        (out / name).write_text(text, encoding="utf-8")
        load_file(out / name)
    return out
