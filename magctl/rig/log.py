"""Run logs: append-only JSON-lines streams of documents, read back, exported and replayed.

A run log is one JSON document per line, in the spirit of Bluesky's event model:

* ``start`` — task, resolved options, seed, the text of every parameter file, limits, magctl version, rig;
* ``descriptor`` — every event field with its shape and unit;
* ``event`` — one per frame: observation, controller command (raw and as sent), task outputs, timing;
* ``stop`` — exit status and counters. A log without ``stop`` is a run that crashed.

Every document is flushed when written, so a process killed with SIGKILL loses
at most the line being written; :func:`read_log` drops a torn last line and
reads everything before it.

Every document is checked against :data:`SCHEMA` (JSON Schema, one sub-schema per document
kind) when it is written and when it is read: a reader gets either documents of the documented
shape or a one-line :class:`LogError` naming the file, the line and the field.

Floats are written with Python's shortest round-trip ``repr``, so logged values
read back bit for bit; :func:`replay` relies on it to feed the logged
observations through a freshly built controller and compare the commands
exactly. A run that planned off the frame is replayed with its plans merged at the ticks its events say
(``outputs.event_applied``), so a real-time run, whose plans came back late, replays exactly too.

**Parts.** A log has a size cap per file (``max_bytes``, ``models/rig.toml`` [log] ``max_mb`` by
default): an event that would take the file ``LOG`` past it goes to ``LOG.1`` instead, then ``LOG.2``…
Each part starts with the run's start document (same ``uid``, with ``part`` and ``first_seq``) and its
descriptor, so it reads alone; the stop document is always written, to the current part. :func:`read_log`
given ``LOG`` reads the parts that follow it as one run.

**Write errors.** An ``OSError`` while writing (a full disk, an I/O error) raises :class:`LogWriteError`
naming the file (also a :class:`~magctl.rig.interface.RigError`); the runtime catches :class:`LogError` and
ends the run as on a rig error — coils zeroed, exit status ``error``, the reason naming the file — and the log
ends at its last complete line, without a stop document.
"""

from __future__ import annotations

import json
import os
import time
import uuid
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from magctl import __version__
from magctl.core.errors import MagctlError
from magctl.rig import protocol as P
from magctl.rig.interface import CoilMap, Command, Observation, RigError, RigLimits

FORMAT = "magctl-runlog/1"


class LogError(MagctlError):
    """A run log cannot be written, read, exported or replayed."""


class LogWriteError(LogError, RigError):
    """Writing the run log failed (disk full, I/O error, a part that exists): the run must stop.

    Also a :class:`~magctl.rig.interface.RigError`, so that the runtime stops the run safely (coils zeroed,
    exit status ``error``, the message naming the file) as it does on a rig error."""


def default_part_bytes() -> int:
    """The part size of models/rig.toml [log] max_mb, in bytes (MB = 10^6 bytes)."""
    from magctl.config import load_model

    mb = load_model("rig").log.max_mb
    if not mb > 0:
        raise LogError(f"models/rig.toml: log.max_mb_1 = {mb!r} must be > 0")
    return int(mb * 1e6)


def part_path(path, k: int) -> Path:
    """File of part ``k`` of the log ``path``: the log itself for 0, else ``path`` + ``.k`` (``run.jsonl.2``),
    so that ``*.jsonl`` matches first parts only."""
    path = Path(path)
    return path if k == 0 else path.with_name(f"{path.name}.{k}")


def _dumps(doc: dict) -> str:
    return json.dumps(doc, allow_nan=False, separators=(",", ":"))


# --- schema ------------------------------------------------------------------------------------------
_NUM = {"type": "number"}
_INT = {"type": "integer"}
_XY = {"type": "array", "items": _NUM, "minItems": 2, "maxItems": 2}
_CMD = {"type": ["object", "null"], "required": ["b_static_T", "b_osc_T", "freq_Hz"],
        "properties": {"b_static_T": _XY, "b_osc_T": _NUM, "freq_Hz": _NUM}}
SCHEMA: dict = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "$id": "https://magctl/runlog/1",
    "title": f"{FORMAT} document",
    "type": "object",
    "required": ["doc"],
    "properties": {"doc": {"enum": ["start", "descriptor", "event", "stop"]}},
    "allOf": [
        {"if": {"properties": {"doc": {"const": "start"}}}, "then": {
            "required": ["format", "uid", "time_unix", "magctl_version", "task", "options", "seed", "rig",
                         "limits"],
            "properties": {
                "format": {"const": FORMAT}, "uid": {"type": "string", "minLength": 1}, "time_unix": _NUM,
                "magctl_version": {"type": "string"}, "task": {"type": "string", "minLength": 1},
                "options": {"type": "object"}, "seed": _INT, "rig": {"type": "object"},
                "limits": {"type": "object", "required": ["b_static_max_T", "b_osc_max_T", "freq_max_Hz"],
                           "properties": {"b_static_max_T": _NUM, "b_osc_max_T": _NUM, "freq_max_Hz": _NUM}},
                "models_toml": {"type": "object", "additionalProperties": {"type": "string"}},
                "period_s": {"type": "number", "exclusiveMinimum": 0}, "realtime": {"type": "boolean"},
                "argv": {"type": "array", "items": {"type": "string"}},
                "part": {"type": "integer", "minimum": 0}, "first_seq": {"type": "integer", "minimum": 0}}}},
        {"if": {"properties": {"doc": {"const": "descriptor"}}}, "then": {
            "required": ["run", "fields"],
            "properties": {"run": {"type": "string"}, "fields": {"type": "object", "additionalProperties": {
                "type": "object", "required": ["shape", "unit"],
                "properties": {"shape": {"type": "array", "items": {"type": "integer", "minimum": 0}},
                               "unit": {"type": "string"}}}}}}},
        {"if": {"properties": {"doc": {"const": "event"}}}, "then": {
            "required": ["seq", "activation", "obs", "cmd_raw", "cmd", "outputs", "timing"],
            "properties": {
                "seq": {"type": "integer", "minimum": 0}, "activation": {"type": "integer", "minimum": 0},
                "obs": {"type": "object",
                        "required": ["t_s", "frame", "robot_est_m", "heading_est_rad", "spheres_est_m", "lost",
                                     "currents_A"],
                        "properties": {"t_s": _NUM, "frame": _INT, "robot_est_m": _XY, "heading_est_rad": _NUM,
                                       "spheres_est_m": {"type": "array", "items": _XY}, "lost": {"type": "boolean"},
                                       "currents_A": {"type": "array", "items": _NUM}}},
                "cmd_raw": _CMD, "cmd": _CMD,
                "outputs": {"type": "object",
                            "additionalProperties": {"type": ["number", "boolean", "array", "null"]}},
                "timing": {"type": "object", "additionalProperties": _NUM},
                "error": {"type": "string"}, "paused": {"type": "boolean"},
                "control": {"type": "array", "items": {
                    "type": "object", "required": ["action", "by"],
                    "properties": {"action": {"enum": ["stop", "pause", "resume"]}, "by": {"type": "string"}}}}}}},
        {"if": {"properties": {"doc": {"const": "stop"}}}, "then": {
            "required": ["run", "time_unix", "exit_status", "reason", "n_events"],
            "properties": {"run": {"type": "string"}, "time_unix": _NUM, "exit_status": {"type": "string"},
                           "reason": {"type": "string"}, "n_events": {"type": "integer", "minimum": 0}}}},
    ],
}
_checks: dict = {}
_explainers: dict = {}


def _branches() -> dict:
    """Each document kind's sub-schema (the matching ``then`` branch of :data:`SCHEMA`), None: the whole schema."""
    kinds = {None: SCHEMA}
    for branch in SCHEMA["allOf"]:
        kinds[branch["if"]["properties"]["doc"]["const"]] = {**branch["then"], "type": "object"}
    return kinds


def _check(kind):
    """The compiled check of one document kind (``fastjsonschema``; its cost beside ``jsonschema``'s:
    benchmarks/bench_runlog.py): raises ``JsonSchemaException`` on an invalid document. The schema keeps to
    keywords whose meaning is the same in drafts 7 and 2020-12, so the draft-7 compiler checks it as written."""
    if not _checks:
        import fastjsonschema

        for k, schema in _branches().items():
            _checks[k] = fastjsonschema.compile({key: v for key, v in schema.items() if key != "$schema"})
    return _checks.get(kind, _checks[None])


def _explainer(kind):
    """The ``jsonschema`` validator of one document kind: the field and the reason of a document the check
    refused."""
    if not _explainers:
        import jsonschema

        jsonschema.Draft202012Validator.check_schema(SCHEMA)
        _explainers.update({k: jsonschema.Draft202012Validator(v) for k, v in _branches().items()})
    return _explainers.get(kind, _explainers[None])


def schema_error(doc) -> str | None:
    """None when ``doc`` is a valid run-log document, else one line naming the field and the problem."""
    if not isinstance(doc, dict):
        return f"a document must be a JSON object, got {type(doc).__name__}"
    import fastjsonschema

    kind = doc.get("doc") if isinstance(doc.get("doc"), str) else None
    try:
        _check(kind)(doc)
        return None
    except fastjsonschema.JsonSchemaException as refused:
        errors = list(_explainer(kind).iter_errors(doc))
        if not errors:            # the two readings of the schema differ: say what the check found
            return f"{doc.get('doc', '?')} document: {refused.message}"
    err = min(errors, key=lambda e: len(list(e.absolute_path)))
    where = ".".join(str(x) for x in err.absolute_path) or "document"
    msg = err.message if len(err.message) <= 160 else err.message[:157] + "..."
    return f"{doc.get('doc', '?')} document, {where}: {msg}"


class RunLogWriter:
    """Append-only writer of one run log.

    Parameters
    ----------
    path : str or Path
        File to create; an existing file is an error (logs are never overwritten).
    fsync : bool
        Also ``fsync`` after every frame (survives power loss, not only process death).
    max_bytes : int, optional
        Size cap of one part, bytes: an event that would take the current file past it opens the next part
        (``path.1``, ``path.2``…, each starting with the start document and the descriptor). None:
        ``models/rig.toml`` [log] ``max_mb`` (the runtime passes its run's own: ``Runtime(log_max_bytes=…)``);
        0: no cap.
        A part always holds at least one event, and the stop document always goes to the current part.

    Every write error (``OSError``: disk full, I/O error) raises :class:`LogWriteError` naming the file;
    after one, the writer writes nothing more (the file ends at its last complete line) and :meth:`stop`
    only closes it.
    """

    def __init__(self, path, fsync: bool = False, *, max_bytes: int | None = None):
        self.path = Path(path)
        self.fsync = fsync
        if max_bytes is None:
            max_bytes = default_part_bytes()
        if not (isinstance(max_bytes, (int, float)) and max_bytes >= 0):
            raise LogError(f"{self.path}: the part size cap must be a number of bytes >= 0, got {max_bytes!r}")
        self.max_bytes = int(max_bytes)
        if self.max_bytes and part_path(self.path, 1).exists():
            # the parts of this log would land on another log's: refuse before the run, not at the first rotation
            raise LogError(f"{part_path(self.path, 1)} exists (a part of an earlier run log?); the run log "
                           f"{self.path} would continue into it: choose another name or move it away")
        try:
            self._fh = open(self.path, "xb")
        except FileExistsError:
            raise LogError(f"{self.path}: run log exists; logs are append-only and never overwritten") from None
        except OSError as err:
            raise LogError(f"{self.path}: cannot create run log: {err}") from None
        self.uid = uuid.uuid4().hex
        self.n_events = 0
        self.closed = False
        self.failed: str | None = None
        self.part = 0
        self.current = self.path
        self.parts = [self.path]
        self._part_bytes = self._part_events = 0
        self._start_doc: dict | None = None
        self._descriptor_doc: dict | None = None

    def _fail(self, path, err) -> LogWriteError:
        why = err.strerror if isinstance(err, OSError) and err.strerror else str(err)
        self.failed = (f"{path}: cannot write the run log ({why}); the run is stopped and the log ends at its "
                       f"last complete line")
        return LogWriteError(self.failed)

    def _put(self, data: bytes) -> None:
        if self.failed is not None:
            raise LogWriteError(self.failed)
        try:
            self._fh.write(data)
            self._fh.flush()
            if self.fsync:
                os.fsync(self._fh.fileno())
        except OSError as err:
            raise self._fail(self.current, err) from None
        self._part_bytes += len(data)

    def _next_part(self) -> None:
        """Close the current part and open the next one with the start document and the descriptor."""
        k = self.part + 1
        path = part_path(self.path, k)
        try:
            fh = open(path, "xb")
        except FileExistsError:
            raise self._fail(path, "the file exists") from None
        except OSError as err:
            raise self._fail(path, err) from None
        old, self._fh = self._fh, fh
        try:
            old.close()
        except OSError as err:
            raise self._fail(self.current, err) from None
        self.part, self.current = k, path
        self.parts.append(path)
        self._part_bytes = self._part_events = 0
        if self._start_doc is not None:
            self._put(self._line({**self._start_doc, "part": k, "first_seq": self.n_events}))
        if self._descriptor_doc is not None:
            self._put(self._line(self._descriptor_doc))

    def _line(self, doc: dict) -> bytes:
        bad = schema_error(doc)
        if bad is not None:
            raise LogError(f"{self.current}: refusing to write an invalid {bad}")
        try:
            return (_dumps(doc) + "\n").encode("utf-8")
        except ValueError:
            where = doc.get("doc") + (f" seq {doc['seq']}" if "seq" in doc else "")
            raise LogError(f"{self.current}: refusing to write {where}: {_non_finite(doc)} is not a finite number "
                           "(JSON has no NaN or infinity)") from None

    def _write(self, doc: dict) -> None:
        data = self._line(doc)
        event = doc.get("doc") == "event"
        if event and self.max_bytes and self._part_events and self._part_bytes + len(data) > self.max_bytes:
            self._next_part()
        self._put(data)
        if event:
            self._part_events += 1

    def start(self, **fields) -> dict:
        doc = start_document(self.uid, **fields)
        self._write(doc)
        self._start_doc = doc
        return doc

    def descriptor(self, fields: dict[str, dict]) -> dict:
        doc = {"doc": "descriptor", "run": self.uid, "fields": fields}
        self._write(doc)
        self._descriptor_doc = doc
        return doc

    def event(self, seq: int, obs: Observation, cmd_raw: Command | None, cmd: Command | None,
              outputs: dict[str, Any], timing: dict[str, float], activation: int, error: str | None = None,
              **extra) -> dict:
        """Write one frame's event document (:func:`event_document`) and return it."""
        doc = event_document(seq, obs, cmd_raw, cmd, outputs, timing, activation, error, **extra)
        self._write(doc)
        self.n_events += 1
        return doc

    def stop(self, exit_status: str, reason: str = "", **fields) -> None:
        """Write the stop document (to the current part, whatever its size) and close; after a write error,
        only close (the log then has no stop document, which readers report)."""
        if self.closed:
            return
        try:
            if self.failed is None:
                self._write({"doc": "stop", "run": self.uid, "time_unix": time.time(), "exit_status": exit_status,
                             "reason": reason, "n_events": self.n_events, **fields})
        finally:
            self.close()

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        try:
            self._fh.close()
        except (OSError, ValueError) as err:
            # after a write error the buffer may still hold the unwritten rest: nothing more to say
            if self.failed is None:
                raise self._fail(self.current, err) from None


def _non_finite(doc, path: str = "") -> str | None:
    """The path of the first non-finite number in ``doc`` (``obs.robot_est_m[0]``), None if there is none."""
    if isinstance(doc, float) and not np.isfinite(doc):
        return path or "a value"
    items = doc.items() if isinstance(doc, dict) else enumerate(doc) if isinstance(doc, list) else ()
    for key, value in items:
        found = _non_finite(value, f"{path}.{key}" if isinstance(key, str) and path else
                            key if isinstance(key, str) else f"{path}[{key}]")
        if found is not None:
            return found
    return None


def start_document(uid: str, **fields) -> dict:
    """A run's start document (``fields``: task, options, seed, rig, limits, parameter files…)."""
    return {"doc": "start", "format": FORMAT, "uid": uid, "time_unix": time.time(), "magctl_version": __version__,
            **fields}


def event_document(seq: int, obs: Observation, cmd_raw: Command | None, cmd: Command | None,
                   outputs: dict[str, Any], timing: dict[str, float], activation: int, error: str | None = None,
                   **extra) -> dict:
    """One frame's event document, as logged and as the live view receives it. ``extra``: ``paused`` (a tick the
    run was paused: no controller step, ``cmd_raw`` None) and ``control`` (the stop/pause/resume requests the tick
    took, each ``{"action", "by"}``)."""
    doc = {"doc": "event", "seq": seq, "activation": activation, "obs": P.observation_to_wire(obs),
           "cmd_raw": None if cmd_raw is None else P.command_to_wire(cmd_raw),
           "cmd": None if cmd is None else P.command_to_wire(cmd), "outputs": outputs, "timing": timing}
    if error is not None:
        doc["error"] = error
    doc.update({k: v for k, v in extra.items() if v is not None})
    return doc


def descriptor_fields(n_spheres: int, outputs: dict[str, tuple]) -> dict[str, dict]:
    """The descriptor's field table: shape and unit of every logged quantity."""
    f = {
        "obs.t_s": {"shape": [], "unit": "s"}, "obs.frame": {"shape": [], "unit": "1"},
        "obs.robot_est_m": {"shape": [2], "unit": "m"}, "obs.heading_est_rad": {"shape": [], "unit": "rad"},
        "obs.spheres_est_m": {"shape": [n_spheres, 2], "unit": "m"}, "obs.lost": {"shape": [], "unit": "bool"},
        "obs.currents_A": {"shape": [6], "unit": "A"},
    }
    for c in ("cmd_raw", "cmd"):
        f |= {f"{c}.b_static_T": {"shape": [2], "unit": "T"}, f"{c}.b_osc_T": {"shape": [], "unit": "T"},
              f"{c}.freq_Hz": {"shape": [], "unit": "1/s"}}
    for name, (shape, unit) in outputs.items():
        f[f"outputs.{name}"] = {"shape": list(shape), "unit": unit}
    for t in TIMING_FIELDS:
        f[f"timing.{t}"] = {"shape": [], "unit": "s"}
    return f


TIMING_FIELDS = ("scheduled_s", "start_s", "jitter_s", "read_s", "compute_s", "write_s", "skipped")


@dataclass
class RunLog:
    """A run log read back.

    Attributes
    ----------
    start, descriptor, stop : dict or None
        The documents (``stop`` is None when the run crashed).
    events : list of dict
        Event documents in order.
    torn_tail : bool
        The last line was incomplete (the process died while writing it) and was dropped.
    """

    path: Path
    start: dict | None
    descriptor: dict | None
    events: list[dict] = field(default_factory=list)
    stop: dict | None = None
    torn_tail: bool = False
    parts: list[Path] = field(default_factory=list)

    def __post_init__(self):
        if not self.parts:
            self.parts = [self.path]

    @property
    def crashed(self) -> bool:
        return self.stop is None

    @property
    def part(self) -> int:
        """Number of the first part read (0: the log's first file)."""
        return int((self.start or {}).get("part", 0))

    @property
    def first_seq(self) -> int:
        """``seq`` of the first event of the first part read (0 unless a later part was read alone)."""
        return int((self.start or {}).get("first_seq", 0))

    @property
    def complete_to(self) -> dict | None:
        """The last complete event: its ``seq`` and observed ``frame`` (None without events)."""
        if not self.events:
            return None
        e = self.events[-1]
        return {"seq": e["seq"], "frame": e["obs"]["frame"], "events": len(self.events)}

    def crash_note(self) -> str | None:
        """One line saying the run has no stop document and up to where the log is complete."""
        if not self.crashed:
            return None
        c = self.complete_to
        upto = "no events" if c is None else f"complete up to event seq {c['seq']} (frame {c['frame']})"
        torn = "; a torn last line was dropped" if self.torn_tail else ""
        where = self.path if len(self.parts) == 1 else f"{self.path} (last part {self.parts[-1].name})"
        return f"{where}: no stop document: the run crashed or is still running; {upto}{torn}"

    def summary(self) -> dict[str, Any]:
        ev = self.events
        timing = np.array([[e["timing"].get("jitter_s", 0.0), e["timing"].get("compute_s", 0.0)] for e in ev]) \
            if ev else np.zeros((0, 2))
        last = ev[-1] if ev else None
        return {
            "path": str(self.path), "task": (self.start or {}).get("task"),
            "options": readable_options((self.start or {}).get("options")), "events": len(ev),
            "exit_status": None if self.stop is None else self.stop.get("exit_status"),
            "reason": None if self.stop is None else self.stop.get("reason"),
            "crashed": self.crashed, "torn_tail": self.torn_tail, "complete_to": self.complete_to,
            "parts": len(self.parts),
            "note": self.crash_note(),
            "duration_s": round(ev[-1]["timing"]["scheduled_s"] - ev[0]["timing"]["scheduled_s"], 6)
            if len(ev) > 1 else 0.0,
            "jitter_p99_ms": round(float(np.percentile(timing[:, 0], 99) * 1e3), 4) if len(ev) else None,
            "compute_p99_ms": round(float(np.percentile(timing[:, 1], 99) * 1e3), 4) if len(ev) else None,
            "final_robot_um": None if last is None else [_um(x) for x in last["obs"]["robot_est_m"]],
            "final_spheres_um": None if last is None else [[_um(x) for x in s] for s in last["obs"]["spheres_est_m"]],
            "final_outputs": None if last is None else self._readable_outputs(last["outputs"]),
        }

    def _readable_outputs(self, outputs: dict) -> dict[str, Any]:
        """The task's last outputs in µm and µm/s with status and phase names (the descriptor gives units)."""
        from magctl.control.status import STATUS_NAMES

        fields = (self.descriptor or {}).get("fields", {})
        phases = task_phases((self.start or {}).get("task"))
        out: dict[str, Any] = {}
        for key, value in outputs.items():
            unit = fields.get(f"outputs.{key}", {}).get("unit")
            if key == "status":
                out[key] = STATUS_NAMES.get(int(value), f"code {value}")
            elif key == "phase" and phases:
                out[key] = phases.get(int(value), f"code {value}")
            elif unit in _READABLE:
                suffix, factor = _READABLE[unit]
                out[f"{key}_{suffix}"] = _scaled(value, factor)
            elif isinstance(value, float) and value.is_integer() and unit == "1":
                out[key] = int(value)
            else:
                out[key] = value
        return out


# SI unit of a logged field → (key suffix, factor) of the readable summary
_READABLE = {"m": ("um", 1e6), "m/s": ("um_s", 1e6)}


def _um(x: float) -> float:
    """Metres → µm, rounded to the nanometre (the float noise of the SI value is not information)."""
    return round(float(x) * 1e6, 3)


def _scaled(value, factor: float):
    if isinstance(value, list):
        return [_scaled(v, factor) for v in value]
    return None if value is None else round(float(value) * factor, 3)


def task_phases(task: str | None) -> dict[int, str]:
    """Phase names of a push task's ``phase`` output (empty for tasks without phases)."""
    from magctl.control.push.assembly import FrontThenSideAssemblyTask
    from magctl.control.push.front import FrontPushTask
    from magctl.control.push.side import SidePushTask

    if task == "front-side-assemble":
        return FrontThenSideAssemblyTask.phase_names()
    return {"front-push": FrontPushTask.PHASES, "side-push": SidePushTask.PHASES,
            "assemble": SidePushTask.PHASES}.get(task or "", {})


def readable_options(options: dict | None) -> dict[str, Any] | None:
    """Resolved task options (SI, unit-suffixed keys) in µm and µm/s, rounded to the nanometre."""
    if options is None:
        return None
    out = {}
    for key, value in options.items():
        for si, (suffix, factor) in sorted(_READABLE.items(), key=lambda kv: -len(kv[0])):
            tail = "_" + si.replace("/", "_")
            if key.endswith(tail) and not isinstance(value, (str, bool)):
                out[key[: -len(tail)] + "_" + suffix] = _scaled(value, factor)
                break
        else:
            out[key] = value
    return out


def _no_constants(name):
    raise ValueError(f"{name} is not a JSON number")


def read_log(path) -> RunLog:
    """Read a run log; a torn last line is dropped, any other bad line is a :class:`LogError`.

    A log that was split in parts (``LOG``, ``LOG.1``, ``LOG.2``…, see :class:`RunLogWriter`) is read from
    the given part to the last one as one run: each part must be the next one of the same run (its start
    document's ``uid``, ``part`` and ``first_seq``). A later part given alone reads from its first event on.
    """
    log = _read_part(Path(path))
    k = log.start.get("part", 0)
    name = log.path.name
    base = log.path if k == 0 else (log.path.with_name(name[: -len(f".{k}")]) if name.endswith(f".{k}") else None)
    while log.stop is None and base is not None:
        nxt = part_path(base, k + 1)
        if not nxt.is_file():
            break
        if log.torn_tail:
            raise LogError(f"{log.parts[-1]}: its last line is torn, yet the log goes on in {nxt}")
        part = _read_part(nxt)
        st = part.start
        expected = log.first_seq + len(log.events)
        if st.get("uid") != log.start.get("uid") or st.get("part") != k + 1:
            raise LogError(f"{nxt}:1: not part {k + 1} of the run log {base} (run {log.start.get('uid')}): its "
                           f"start document says run {st.get('uid')}, part {st.get('part')}")
        if part.first_seq != expected:
            raise LogError(f"{nxt}:1: part {k + 1} starts at event seq {part.first_seq} where {expected} was "
                           f"expected")
        log.events.extend(part.events)
        log.stop, log.torn_tail = part.stop, part.torn_tail
        log.parts.append(nxt)
        k += 1
    return log


def _read_part(path: Path) -> RunLog:
    """One file of a run log."""
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise LogError(f"{path}: no such run log") from None
    except IsADirectoryError:
        raise LogError(f"{path}: is a directory, not a run log") from None
    except OSError as err:
        raise LogError(f"{path}: cannot read: {err.strerror or err}") from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as err:
        line = data[: err.start].count(b"\n") + 1
        raise LogError(f"{path}:{line}: not UTF-8 text (byte {err.start}); not a magctl run log") from None
    lines = text.split("\n")
    torn = False
    if lines and lines[-1] == "":
        lines.pop()
    elif lines:
        # no final newline: the writer died mid-line
        lines.pop()
        torn = True
    log = RunLog(path, None, None)
    for i, line in enumerate(lines, 1):
        try:
            doc = json.loads(line, parse_constant=_no_constants)
        except json.JSONDecodeError as err:
            raise LogError(f"{path}:{i}: not a JSON document: {err.msg} (column {err.colno})") from None
        except (ValueError, RecursionError) as err:
            raise LogError(f"{path}:{i}: not a valid JSON document: {P.show(str(err), 100)}") from None
        kind = doc.get("doc") if isinstance(doc, dict) else None
        if i == 1 and (kind != "start" or doc.get("format") != FORMAT):
            raise LogError(f"{path}:1: not a magctl run log (expected a start document of format {FORMAT})")
        if i > 1 and kind == "start":
            raise LogError(f"{path}:{i}: a second start document")
        bad = schema_error(doc)
        if bad is not None:
            raise LogError(f"{path}:{i}: {bad}")
        if log.stop is not None:
            raise LogError(f"{path}:{i}: a {kind} document after the stop document")
        if kind == "event" and doc["seq"] != log.first_seq + len(log.events):
            raise LogError(f"{path}:{i}: event seq {doc['seq']} where {log.first_seq + len(log.events)} was "
                           f"expected")
        if kind == "start":
            log.start = doc
        elif kind == "descriptor":
            log.descriptor = doc
        elif kind == "event":
            log.events.append(doc)
        elif kind == "stop":
            log.stop = doc
        else:
            raise LogError(f"{path}:{i}: unknown document kind {kind!r}")
    if log.start is None:
        if torn:
            raise LogError(f"{path}:1: the start document is torn (the run stopped while writing its first line): "
                           "nothing to read")
        raise LogError(f"{path}: empty run log")
    log.torn_tail = torn
    return log


def event_observation(ev: dict) -> Observation:
    try:
        return P.observation_from_wire(ev["obs"])
    except P.ProtocolError as err:
        raise LogError(f"event seq {ev.get('seq')}: {err}") from None


def limits_from_doc(doc: dict) -> RigLimits:
    """The limits a run used, from its start document (the coil allocation is stored in full)."""
    lim = doc["limits"]
    if "coil_pinv" in lim:
        coils = CoilMap(lim["coil_pinv"], lim["coil_current_limit_A"], lim["clamp_gradient_T_m"], lim["coil_names"])
    else:  # logs written before the map came from the actuator: one pair per axis, half the field each
        kxy, kz = lim["k_xy_T_per_A"], lim["k_z_T_per_A"]
        pinv = np.zeros((6, 4))
        pinv[0:2, 0] = pinv[2:4, 1] = 1.0 / (2 * kxy)
        pinv[4:6, 2] = 1.0 / (2 * kz)
        coils = CoilMap(pinv, np.full(6, lim["current_max_A"]))
    return RigLimits(lim["b_static_max_T"], lim["b_osc_max_T"], lim["freq_max_Hz"], coils)


def limits_to_doc(limits: RigLimits) -> dict:
    c = limits.coils
    return {"b_static_max_T": limits.b_static_max, "b_osc_max_T": limits.b_osc_max, "freq_max_Hz": limits.freq_max,
            "current_max_A": c.current_max, "coil_names": list(c.names), "coil_pinv": c.pinv.tolist(),
            "coil_current_limit_A": c.current_limit.tolist(), "clamp_gradient_T_m": c.clamp_gradient}


def models_snapshot(folder) -> dict[str, str]:
    """The text of every parameter file in ``folder`` (``name.toml`` → text), for the start document."""
    return {f.name: f.read_text("utf-8") for f in sorted(Path(folder).glob("*.toml"))}


@contextmanager
def models_from_doc(start: dict):
    """Parameter files of a run, restored from its start document into a temporary ``$MAGCTL_MODELS``.

    Yields the rig parameters. Every ``load_model`` inside the block (servo, drive, push tasks) reads
    the files the run used, so the rebuilt controller is the one that ran.
    """
    import tempfile

    from magctl.config import load_file

    files = start.get("models_toml")
    if not isinstance(files, dict) or "rig.toml" not in files:
        raise LogError("start document has no models_toml with rig.toml; cannot rebuild the controller")
    for name in files:
        # a name from the log becomes a file name: a plain *.toml name only (a NUL, a path separator, a control
        # character or a leading dot would make the OS refuse it or write elsewhere)
        if (not isinstance(name, str) or not name.endswith(".toml") or name.startswith(".") or len(name) > 200
                or any(c in "/\\" or ord(c) < 32 or ord(c) == 127 for c in name)):
            raise LogError(f"start document: models_toml: bad parameter file name {P.show(name, 80)} (a plain "
                           f"NAME.toml is expected)")
    old = os.environ.get("MAGCTL_MODELS")
    with tempfile.TemporaryDirectory() as tmp:
        for name, text in files.items():
            try:
                (Path(tmp) / name).write_text(text, encoding="utf-8")
            except (OSError, ValueError) as err:
                raise LogError(f"start document: models_toml: cannot restore {P.show(name, 80)}: "
                               f"{getattr(err, 'strerror', None) or err}") from None
        os.environ["MAGCTL_MODELS"] = tmp
        try:
            yield load_file(Path(tmp) / "rig.toml")
        except MagctlError as err:
            # a logged file that does not load: name it as the log holds it, not by the temporary folder
            if tmp not in str(err):
                raise
            raise LogError("start document: " + str(err).replace(tmp + os.sep, "models_toml: ")) from None
        finally:
            if old is None:
                os.environ.pop("MAGCTL_MODELS", None)
            else:
                os.environ["MAGCTL_MODELS"] = old


# --- export ------------------------------------------------------------------------------------------
def columns(log: RunLog) -> dict[str, np.ndarray]:
    """The events as flat columns (one value per frame), SI with unit-suffixed names."""
    ev = log.events
    cols: dict[str, list] = {"seq": [], "activation": [], "t_s": [], "frame": [], "robot_x_m": [], "robot_y_m": [],
                             "heading_rad": [], "lost": []}
    n_sph = len(ev[0]["obs"]["spheres_est_m"]) if ev else 0
    for i in range(n_sph):
        cols[f"sphere{i}_x_m"], cols[f"sphere{i}_y_m"] = [], []
    for j in range(6):
        cols[f"current{j}_A"] = []
    for c in ("cmd_raw", "cmd"):
        for k in ("b_static_x_T", "b_static_y_T", "b_osc_T", "freq_Hz"):
            cols[f"{c}_{k}"] = []
    out_names = sorted({k for e in ev for k, v in e["outputs"].items() if not isinstance(v, list)})
    for k in out_names:
        cols[f"out_{k}"] = []
    for t in TIMING_FIELDS:
        cols[t] = []
    nan = float("nan")
    for e in ev:
        o = e["obs"]
        cols["seq"].append(e["seq"])
        cols["activation"].append(e["activation"])
        cols["t_s"].append(o["t_s"])
        cols["frame"].append(o["frame"])
        cols["robot_x_m"].append(o["robot_est_m"][0])
        cols["robot_y_m"].append(o["robot_est_m"][1])
        cols["heading_rad"].append(o["heading_est_rad"])
        cols["lost"].append(o["lost"])
        for i in range(n_sph):
            cols[f"sphere{i}_x_m"].append(o["spheres_est_m"][i][0])
            cols[f"sphere{i}_y_m"].append(o["spheres_est_m"][i][1])
        for j in range(6):
            cols[f"current{j}_A"].append(o["currents_A"][j])
        for c in ("cmd_raw", "cmd"):
            cm = e.get(c)
            vals = (nan,) * 4 if cm is None else (*cm["b_static_T"], cm["b_osc_T"], cm["freq_Hz"])
            for k, v in zip(("b_static_x_T", "b_static_y_T", "b_osc_T", "freq_Hz"), vals, strict=True):
                cols[f"{c}_{k}"].append(v)
        for k in out_names:
            cols[f"out_{k}"].append(e["outputs"].get(k, nan))
        for t in TIMING_FIELDS:
            cols[t].append(e["timing"].get(t, nan))
    arrays = {}
    for k, v in cols.items():
        dtype = bool if k == "lost" else (np.int64 if k in ("seq", "activation", "frame", "skipped") else float)
        arrays[k] = np.asarray(v, dtype=dtype)
    return arrays


def export(log_path, out_path) -> Path:
    """Export a run log to Parquet (``.parquet``) or HDF5 (``.h5``/``.hdf5``); documents go into metadata."""
    log = read_log(log_path)
    out = Path(out_path)
    try:
        cols = columns(log)
    except (IndexError, KeyError, TypeError, ValueError) as err:
        raise LogError(f"{log.path}: events do not share one layout ({type(err).__name__}: {err}); "
                       f"cannot export columns") from None
    meta = {"start": log.start, "descriptor": log.descriptor, "stop": log.stop, "torn_tail": log.torn_tail}
    suffix = out.suffix.lower()
    if suffix == ".parquet":
        try:
            import pyarrow as pa
            import pyarrow.parquet as pq
        except ImportError:
            raise LogError("Parquet export needs pyarrow: pip install 'magctl[export]'") from None

        table = pa.table(cols)
        table = table.replace_schema_metadata({k.encode(): json.dumps(v).encode() for k, v in meta.items()})
        pq.write_table(table, out)
    elif suffix in (".h5", ".hdf5"):
        try:
            import h5py
        except ImportError:
            raise LogError("HDF5 export needs h5py: pip install 'magctl[export]'") from None

        with h5py.File(out, "w") as f:
            g = f.create_group("events")
            for k, v in cols.items():
                g.create_dataset(k, data=v)
            for k, v in meta.items():
                f.attrs[k] = json.dumps(v)
    else:
        raise LogError(f"{out}: unknown export format {suffix!r}; use .parquet, .h5 or .hdf5")
    return out


# --- replay ------------------------------------------------------------------------------------------
@dataclass
class ReplayResult:
    """Outcome of :func:`replay`: commands compared, mismatches (with the first one), identical flag.

    ``merged`` counts the plans (deferred events) merged at the tick the log says (0 for a run that planned
    inside the tick)."""

    events: int
    compared: int
    mismatches: int
    first_mismatch: dict | None
    crashed: bool = False
    complete_to: dict | None = None
    note: str | None = None
    merged: int = 0

    @property
    def identical(self) -> bool:
        return self.mismatches == 0 and self.compared > 0


def deferred_events(log: RunLog) -> bool:
    """Whether the run planned off the frame: its events say when each plan was requested and applied
    (``outputs.event_applied``; docs/rig.md "Planning off the frame")."""
    fields = (log.descriptor or {}).get("fields", {})
    return "outputs.event_applied" in fields or any("event_applied" in e["outputs"] for e in log.events)


def _logged_tick(value) -> int | None:
    """A logged ``event_applied`` as a tick (−1: none), None when it is not a whole number >= −1."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    if isinstance(value, float) and not value.is_integer():
        return None
    return int(value) if value >= -1 else None


def replay(log_path) -> ReplayResult:
    """Feed the logged observations through a freshly built controller; compare commands bit for bit.

    The controller is rebuilt from the start document (task, resolved options,
    seed, and the text of every parameter file the run used) and reset at every change of ``activation``, as the
    runtime did; both the raw controller command and the clipped command sent
    to the rig are compared with ``==`` on the float64 values.

    A run that planned off the frame (its events carry ``outputs.event_applied``) is replayed with the runtime's
    machinery, ``Controller(defer_events=True)``: each plan a step requests is run (here, in the replaying
    thread) and merged before the step of the event whose ``event_applied`` names the requesting tick — the
    tick where the run merged it, however late — so a real-time run replays bit for bit as a lock-step one does.
    The log's ``event_applied``, ``event_pending`` and ``event_requested`` are checked against the replay too: a
    value the replay cannot follow (no plan of that tick pending, not a tick) is a mismatch at that event, and the
    replay goes on. A run without these fields replays with the on-frame controller, as a study steps it.
    """
    from magctl.rig.tasks import Controller, build_task

    log = read_log(log_path)
    st = log.start
    if log.part:
        first = log.path.name[: -len(f".{log.part}")] if log.path.name.endswith(f".{log.part}") else "its first part"
        raise LogError(f"{log.path}: part {log.part} of a run log (from event seq {log.first_seq}); replay runs the "
                       f"controller from the start of the run: give the log's first part, {first}")
    if not log.events:
        raise LogError(f"{log.path}: no events to replay" + (" (no stop document either: the run crashed "
                                                             "before its first frame)" if log.crashed else ""))
    try:
        limits = limits_from_doc(st)
    except (KeyError, TypeError, ValueError, MagctlError) as err:
        raise LogError(f"{log.path}:1: start document: limits unusable ({type(err).__name__}: {err})") from None
    first = event_observation(log.events[0])
    try:
        with models_from_doc(st) as params:
            task = build_task(st["task"], first, st["options"], params)
    except LogError as err:
        raise LogError(f"{log.path}:1: {err}") from None
    deferred = deferred_events(log)
    ctrl = Controller(task, seed=st.get("seed", 0), defer_events=deferred)
    activation = log.events[0]["activation"]
    compared = mismatches = merged = 0
    first_bad = None
    pending: list[tuple[int, Any]] = []   # (seq of the requesting event, request): requested, not merged yet

    def differ(seq: int, key: str, logged, mine) -> None:
        nonlocal mismatches, first_bad
        mismatches += 1
        if first_bad is None:
            first_bad = {"seq": seq, "field": key, "logged": logged, "replayed": mine}

    for e in log.events:
        seq, outs = e["seq"], e["outputs"]
        if e.get("paused"):
            continue   # the run held the robot without stepping the controller (docs/rig.md "Live view")
        if e["activation"] != activation:
            ctrl.reset()
            pending.clear()   # the runtime drops the plans of the last activation too
            activation = e["activation"]
        if deferred:
            # merge what the run merged before this step: the plans requested up to the logged tick, in order
            # (one worker runs them in order, so an earlier plan is never merged after a later one)
            logged = outs.get("event_applied")
            tick = _logged_tick(logged)
            due = [] if tick is None else [p for p in pending if p[0] <= tick]
            if tick is None or (tick >= 0 and (not due or due[-1][0] != tick)):
                differ(seq, "outputs.event_applied", logged, due[-1][0] if due else -1)
            for requested, req in due:
                try:
                    result = req.run()
                except Exception as err:  # noqa: BLE001 - the planner's own failure, named in one line
                    raise LogError(f"{log.path}: event seq {seq}: the plan requested at seq {requested} fails on "
                                   f"replay ({type(err).__name__}: {P.show(str(err), 120)})") from None
                ctrl.apply(req, result)
                merged += 1
            pending = pending[len(due):]   # the due ones are the oldest
            if "event_pending" in outs and outs["event_pending"] != bool(pending):
                differ(seq, "outputs.event_pending", outs["event_pending"], bool(pending))
        if e.get("cmd_raw") is None:
            continue
        raw, _ = ctrl.step(event_observation(e))
        sent = limits.clip(raw)
        for key, cmd in (("cmd_raw", raw), ("cmd", sent)):
            if e.get(key) is None:
                continue
            compared += 1
            mine = P.command_to_wire(cmd)
            if mine != e[key]:
                differ(seq, key, e[key], mine)
        if deferred:
            new = ctrl.take_requests()
            pending += [(seq, req) for req in new]
            if outs.get("event_requested") != len(new):
                differ(seq, "outputs.event_requested", outs.get("event_requested"), len(new))
    return ReplayResult(len(log.events), compared, mismatches, first_bad, log.crashed, log.complete_to,
                        log.crash_note(), merged)
