"""The compiled engine: one generated, numba-compiled step — and one loop over trials and steps — for a
whole diagram whose every leaf block has a kernel (:mod:`magctl.core.kernel`).

``compile_diagram(diagram)`` (``Diagram.compile()``) lays the diagram's values out in a few flat
buffers by dtype (parameters, state, next state, outputs, the diagram's inputs), generates Python
source that calls every leaf's kernel in the schedule's order — feedthrough outputs first, then the
updates of the blocks without feedthrough, then the new state; a leaf of period ``r`` base ticks
runs when ``tick % r == 0`` and holds its outputs in between — and compiles it with numba. The
source is written to :func:`magctl.core.codegen.cache_dir` under a hash of
its text, so numba's on-disk cache serves the next run; parameters are data, not code, so two
diagrams that differ only in their gains share the compiled code.

Semantics are the interpreted engine's (:meth:`magctl.core.schedule.Schedule.run`): same order of
evaluation, same per-trial random streams (counter-based: each kernel reads its numbers by address,
:mod:`magctl.core.philox`), same results to floating-point reassociation. The loop runs trial by trial
(each trial's steps in turn), which changes nothing since trials never interact.

It reads the diagram's schedule (:mod:`magctl.core.schedule`) and does not import :mod:`magctl.core.diagram`,
whose ``Diagram.compile()`` calls it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magctl.core import codegen
from magctl.core.codegen import JIT, fingerprint, is_record, kernel_name, param_value
from magctl.core.errors import MagctlError
from magctl.core.kernel import (
    EventRequest,
    Kernel,
    compiled_vars,
    event_index,
    handle_events,
    merge_event,
    pack_state,
    port_width,
    stream_keys_of,
    unpack_state,
)
from magctl.core.schedule import EXTERNAL

GROUPS = {"float64": "F", "int64": "I", "bool": "B"}
"""Buffer of each dtype."""

class NotCompilable(MagctlError):
    """A diagram the compiled engine cannot run; the message names the block and why."""


def _group(dtype) -> str:
    name = np.dtype(dtype).name
    if name not in GROUPS:
        raise NotCompilable(f"dtype {name} has no compiled buffer (float64, int64, bool only)")
    return GROUPS[name]


@dataclass
class _Slot:
    """Where one ``(B, n)`` value lives: buffer letter, offset in units of B, width n."""

    group: str
    offset: int
    width: int

    def view(self, buf: str) -> str:
        return f"{buf}{self.group}[B * {self.offset}:B * {self.offset + self.width}].reshape(B, {self.width})"


class _Layout:
    """Offsets of ``(B, n)`` values packed into one flat buffer per dtype."""

    def __init__(self):
        self.used = {g: 0 for g in GROUPS.values()}

    def add(self, dtype, width: int) -> _Slot:
        g = _group(dtype)
        slot = _Slot(g, self.used[g], width)
        self.used[g] += width
        return slot

    def buffers(self, batch: int) -> dict[str, np.ndarray]:
        dt = {"F": np.float64, "I": np.int64, "B": np.bool_}
        return {g: np.zeros(batch * n, dtype=dt[g]) for g, n in self.used.items()}


def _param_expr(value, pbufs: dict[str, list], name: str, imports: dict) -> str:
    """Source that rebuilds one kernel parameter from the flat parameter buffers (filled in ``pbufs``); a named
    tuple is rebuilt field by field with its class (added to ``imports``)."""
    if is_record(value):
        cls = type(value)
        alias = f"R_{cls.__name__}"
        imports[alias] = (cls.__module__, cls.__qualname__)
        return f"{alias}({', '.join(_param_expr(v, pbufs, name, imports) for v in value)})"
    arr = np.asarray(value)
    if isinstance(value, (bool, np.bool_)):
        g = "B"
    elif arr.dtype.kind in "iu":
        g = "I"
    elif arr.dtype.kind == "b":
        g = "B"
    elif arr.dtype.kind == "f":
        g = "F"
    else:
        raise NotCompilable(f"{name}: kernel parameter of dtype {arr.dtype} (float, int and bool only)")
    start = len(pbufs[g])
    pbufs[g].extend(arr.ravel().tolist())
    if arr.ndim == 0:
        return f"P{g}[{start}]"
    shape = ", ".join(str(n) for n in arr.shape)
    return f"P{g}[{start}:{start + arr.size}].reshape(({shape},))"


def _tuple(items: list[str]) -> str:
    if not items:
        return "()"
    return "(" + ", ".join(items) + ("," if len(items) == 1 else "") + ")"


class CompiledDiagram:
    """A diagram compiled into one generated step and one generated simulation loop.

    Build it with :func:`compile_diagram` (``Diagram.compile()``); :func:`magctl.core.simulation.simulate`
    uses it with ``engine="compiled"``, and :meth:`stepper` gives the one-call-per-frame form the rig
    runs.
    """

    def __init__(self, diagram):
        self.diagram = diagram
        sched = self.schedule = diagram.schedule
        self.kernels: list[Kernel] = []
        for lf in sched.leaves:
            k = lf.block.kernel()
            if k is None:
                raise NotCompilable(f"block {lf.path!r} ({type(lf.block).__name__}) has no compiled kernel; "
                                    "the interpreted engine runs this diagram")
            if (k.step is not None) != bool(lf.block.feedthrough):
                raise NotCompilable(f"block {lf.path!r}: its kernel's form does not match its feedthrough")
            self.kernels.append(k)
        self._generate()
        self._module = None

    # --- layout and source ------------------------------------------------------------------------
    def _generate(self) -> None:
        sched, kernels = self.schedule, self.kernels
        state, outs, ext = _Layout(), _Layout(), _Layout()
        pbufs: dict[str, list] = {g: [] for g in GROUPS.values()}
        self.vars = [compiled_vars(lf.block) for lf in sched.leaves]
        self.state_slots = [[state.add(v.dtype, v.size) for _, v in variables] for variables in self.vars]
        self.out_slots = [{p: outs.add(port.dtype, port_width(port)) for p, port in lf.block.outputs.items()}
                          for lf in sched.leaves]
        self.ext_slots = {name: ext.add(port.dtype, port_width(port)) for name, port in sched.inputs.items()}
        self.state_layout, self.out_layout, self.ext_layout = state, outs, ext
        imports: dict[str, tuple[str, str]] = {}
        param_exprs = [_tuple([_param_expr(v, pbufs, f"block {lf.path!r}", imports) for v in k.params])
                       for lf, k in zip(sched.leaves, kernels, strict=True)]
        dt = {"F": np.float64, "I": np.int64, "B": np.bool_}
        self.params = {g: np.asarray(v, dtype=dt[g]) if v else np.zeros(1, dtype=dt[g]) for g, v in pbufs.items()}
        self.param_tuples = tuple(tuple(param_value(v) for v in k.params) for k in kernels)
        self.noisy = [i for i, k in enumerate(kernels) if k.stream]
        self.events = {i: event_index(lf.block, k, self.vars[i])
                       for i, (lf, k) in enumerate(zip(sched.leaves, kernels, strict=True)) if k.event}

        views = []
        for i, k in enumerate(kernels):
            for role, fn in (("step", k.step), ("output", k.output), ("update", k.update)):
                if fn is not None:
                    mod, qual = kernel_name(fn)
                    imports[f"k{i}_{role}"] = (mod, qual)
            views.append(f"p{i} = PARAMS")
            for v, slot in enumerate(self.state_slots[i]):
                views.append(f"s{i}_{v} = {slot.view('S')}")
                if not k.in_place:
                    views.append(f"n{i}_{v} = {slot.view('N')}")
            for p, slot in self.out_slots[i].items():
                views.append(f"o{i}_{p} = {slot.view('O')}")
        for name, slot in self.ext_slots.items():
            views.append(f"x_{name} = {slot.view('X')}")
        for j, i in enumerate(self.noisy):
            views.append(f"z{i} = NOISE[{j}]")

        def inputs_of(i: int) -> str:
            return _tuple([f"x_{q}" if j == EXTERNAL else f"o{j}_{q}" for _, j, q in sched.leaves[i].wiring])

        def call_args(i: int) -> dict[str, str]:
            n_state = len(self.state_slots[i])
            nxt = "s" if kernels[i].in_place else "n"
            return {"params": f"p{i}",
                    "state": _tuple([f"s{i}_{v}" for v in range(n_state)]),
                    "next": _tuple([f"{nxt}{i}_{v}" for v in range(n_state)]),
                    "inputs": inputs_of(i),
                    "outputs": _tuple([f"o{i}_{p}" for p in lf_outputs(i)]),
                    "noise": f"0, z{i}" if i in self.noisy else "0, ()"}

        def lf_outputs(i: int) -> list[str]:
            return list(sched.leaves[i].block.outputs)

        tick_lines = []
        multirate = [i for i, lf in enumerate(sched.leaves) if lf.ratio != 1]
        runs = {i: (f"(tick % {sched.leaves[i].ratio} == 0 or not ran{i})" if i in multirate else "True")
                for i in range(len(sched.leaves))}
        for i, k in enumerate(kernels):
            a = call_args(i)
            cond = runs[i]
            if i in multirate:
                tick_lines.append(f"go{i} = {cond}")
                cond = f"go{i}"
            call = (f"k{i}_step(b, {a['params']}, {a['state']}, {a['next']}, {a['inputs']}, {a['outputs']}, "
                    f"{a['noise']})" if k.step is not None else
                    f"k{i}_output(b, {a['params']}, {a['state']}, {a['outputs']})")
            tick_lines += _guarded(cond, [call])
        for i, k in enumerate(kernels):
            if k.update is not None:
                a = call_args(i)
                cond = f"go{i}" if i in multirate else "True"
                tick_lines += _guarded(cond, [f"k{i}_update(b, {a['params']}, {a['state']}, {a['next']}, "
                                              f"{a['inputs']}, {a['noise']})"])
        for i, slots in enumerate(self.state_slots):
            copies = [] if kernels[i].in_place else \
                [f"for c in range({s.width}):\n    s{i}_{v}[b, c] = n{i}_{v}[b, c]" for v, s in enumerate(slots)]
            if i in multirate:
                copies.append(f"ran{i} = True")
            if copies:
                tick_lines += _guarded(f"go{i}" if i in multirate else "True", copies)

        self.record_names = [f"{lf.path}.{p}" for lf in sched.leaves for p in lf.block.outputs]
        rec_source = {f"{lf.path}.{p}": f"o{i}_{p}" for i, lf in enumerate(sched.leaves) for p in lf.block.outputs}
        self._rec_source = rec_source

        head = [f"# generated by magctl.core.compiled; kernel sources {fingerprint(m for m, _ in imports.values())}",
                "import numba", "import numpy as np"]
        head += [f"from {mod} import {qual} as {alias}" for alias, (mod, qual) in sorted(imports.items())]
        args = "B, AF, AI, AB, BASE, NOISE, RAN"
        regions = [f"{name}{g} = A{g}[BASE[{row}, {r}]:BASE[{row}, {r + 1}]]"
                   for row, g in enumerate("FIB") for r, name in enumerate("PSNOX")]
        views = regions + views
        # run_steps takes the parameters as built tuples (views made in Python: faster loops); step_once,
        # called once per frame, rebuilds them from the flat buffers (fewer arguments to unbox per call)
        run_views = [f"p{v.split(' ')[0][1:]} = PT[{v.split(' ')[0][1:]}]" if v.endswith("= PARAMS") else v
                     for v in views]
        step_views = [f"{v.split(' ')[0]} = {param_exprs[int(v.split(' ')[0][1:])]}" if v.endswith("= PARAMS")
                      else v for v in views]
        # an event flag raised in a tick stops the loop after that tick's record: run_steps returns 1 with
        # STOP = (trial, next step, leaf), Python handles the event and calls it again from there
        event_lines = []
        for i, v in self.events.items():
            event_lines += [f"if s{i}_{v}[b, 0]:", "    STOP[0] = b", "    STOP[1] = k + 1", f"    STOP[2] = {i}"]
            event_lines += [f"    RANT[{j}] = ran{j}" for j in multirate]
            event_lines += ["    return 1"]
        lines = head + ["", "", JIT,
                        f"def run_steps(B0, K0, STOP, RANT, T, tick0, EXT, RECOFF, RECF, RECI, RECB, PT, {args}):"]
        lines += _indent(run_views, 1)
        lines += _indent([f"ran{i} = RAN[{i}]" for i in multirate], 1)
        lines += ["    for b in range(B0, B):", "        resumed = b == B0 and K0 > 0"]
        lines += _indent([f"ran{i} = RANT[{i}] if resumed else RAN[{i}]" for i in multirate], 2)
        lines += ["        for k in range(K0 if resumed else 0, T):", "            tick = tick0 + k"]
        for e, (name, slot) in enumerate(self.ext_slots.items()):
            lines += [f"            for c in range({slot.width}):",
                      f"                x_{name}[b, c] = EXT[{e}][b, k, c]"]
        lines += _indent(tick_lines, 3)
        lines += _indent(self._record_lines(), 3)
        lines += _indent(event_lines, 3)
        lines += ["    return 0", "", "", JIT,
                  f"def step_once(tick, {args}):"]
        lines += _indent(step_views, 1)
        lines += ["    for b in range(B):"]
        lines += _indent([f"ran{i} = RAN[{i}]" for i in multirate], 2)
        lines += _indent(tick_lines, 2)
        lines += _indent([f"RAN[{i}] = ran{i}" for i in multirate], 2)
        lines += ["    return 0", ""]
        self.source = "\n".join(lines)
        self.multirate = multirate

    def _record_lines(self) -> list[str]:
        """Copy the recorded outputs into the record buffers (one per dtype, ``(B, T, width)``) at the columns
        ``RECOFF`` gives (−1: not recorded), so what is recorded changes no type and compiles nothing."""
        lines = []
        for j, name in enumerate(self.record_names):
            src = self._rec_source[name]
            i, p = self._leaf_port(name)
            slot = self.out_slots[i][p]
            lines += [f"if RECOFF[{j}] >= 0:",
                      f"    for c in range({slot.width}):",
                      f"        REC{slot.group}[b, k, RECOFF[{j}] + c] = {src}[b, c]"]
        return lines

    def _leaf_port(self, name: str) -> tuple[int, str]:
        path, port = name.rsplit(".", 1)
        for i, lf in enumerate(self.schedule.leaves):
            if lf.path == path:
                return i, port
        raise KeyError(name)

    # --- loading --------------------------------------------------------------------------------
    def module(self):
        """The generated module, written to the cache folder and imported (numba compiles it on first use)."""
        if self._module is None:
            self._module = codegen.load(self.source)
        return self._module

    # --- buffers --------------------------------------------------------------------------------
    def _buffers(self, state: dict, batch: int) -> dict:
        """The run's buffers: per dtype one contiguous array holding the parameters, state, next state, outputs
        and diagram inputs one after the other (``"A"``; ``"base"``: where each region starts), so a compiled
        call unboxes three arrays instead of fifteen; ``"P"``, ``"S"``, ``"N"``, ``"O"``, ``"X"`` are views of
        the regions by dtype."""
        sched = self.schedule
        dt = {"F": np.float64, "I": np.int64, "B": np.bool_}
        sizes = {g: [self.params[g].size] + [batch * layout.used[g] for layout in
                                            (self.state_layout, self.state_layout, self.out_layout, self.ext_layout)]
                 for g in GROUPS.values()}
        A = {g: np.zeros(sum(sizes[g]), dtype=dt[g]) for g in GROUPS.values()}
        base = np.zeros((3, 6), dtype=np.int64)
        regions = {name: {} for name in "PSNOX"}
        for row, g in enumerate("FIB"):
            base[row, 1:] = np.cumsum(sizes[g])
            for r, name in enumerate("PSNOX"):
                regions[name][g] = A[g][base[row, r]:base[row, r + 1]]
        P, S, O = regions["P"], regions["S"], regions["O"]
        for g in GROUPS.values():
            P[g][:] = self.params[g]
        for i, lf in enumerate(sched.leaves):
            packed = pack_state(lf.block, state["leaves"][i], batch, self.vars[i])
            for slot, arr in zip(self.state_slots[i], packed, strict=True):
                S[slot.group][batch * slot.offset:batch * (slot.offset + slot.width)] = arr.ravel()
        for g in GROUPS.values():
            regions["N"][g][:] = S[g]
        ran = np.zeros(len(sched.leaves), dtype=np.bool_)
        for i, held in enumerate(state["held"]):
            if held is None or i not in self.multirate:
                continue
            ran[i] = True
            for p, slot in self.out_slots[i].items():
                O[slot.group][batch * slot.offset:batch * (slot.offset + slot.width)] = \
                    np.asarray(held[p]).reshape(batch, -1).ravel()
        return {**regions, "A": A, "base": base, "ran": ran}

    def _noise(self, state: dict, batch: int) -> tuple:
        """The stream key rows of every noisy leaf, in the order of :attr:`noisy`."""
        return tuple(stream_keys_of(self.kernels[i], state["leaves"][i], batch) for i in self.noisy)

    def _args(self, buf: dict, batch: int, noise) -> tuple:
        A = buf["A"]
        return batch, A["F"], A["I"], A["B"], buf["base"], noise, buf["ran"]

    def _unpack(self, buf: dict, state: dict, batch: int) -> dict:
        sched = self.schedule
        leaves = []
        for i, lf in enumerate(sched.leaves):
            arrays = [buf["S"][s.group][batch * s.offset:batch * (s.offset + s.width)].reshape(batch, s.width)
                      for s in self.state_slots[i]]
            leaves.append(unpack_state(lf.block, arrays, state["leaves"][i], self.vars[i]))
        return leaves

    def _event_arrays(self, buf: dict, batch: int, i: int, rows: np.ndarray) -> tuple[list, dict]:
        """Leaf ``i``'s state arrays (views of the buffers) and the inputs of the trials ``rows`` in the last tick
        (copies: still in the output buffers until the next tick)."""
        lf = self.schedule.leaves[i]

        def rows_of(group_bufs, slot):
            return group_bufs[slot.group][batch * slot.offset:batch * (slot.offset + slot.width)].reshape(
                batch, slot.width)

        arrays = [rows_of(buf["S"], s) for s in self.state_slots[i]]
        inputs = {}
        for port, j, q in lf.wiring:
            slot = self.ext_slots[q] if j == EXTERNAL else self.out_slots[j][q]
            src = rows_of(buf["X"] if j == EXTERNAL else buf["O"], slot)
            inputs[port] = src[rows].reshape((rows.size, *lf.block.inputs[port].shape))
        return arrays, inputs

    def handle_events(self, buf: dict, state: dict, batch: int, i: int, rows: np.ndarray) -> None:
        """Leaf ``i``'s Python event handler for the trials ``rows``, on the compiled buffers: their state
        rows and the inputs the leaf saw in the tick that raised the flag (still in the output buffers)."""
        lf = self.schedule.leaves[i]
        arrays, inputs = self._event_arrays(buf, batch, i, rows)
        handle_events(lf.block, arrays, inputs, rows, state["leaves"][i], self.events[i], self.vars[i])

    def event_request(self, buf: dict, state: dict, batch: int, i: int, rows: np.ndarray, tick: int) -> EventRequest:
        """What leaf ``i``'s handler needs for the trials ``rows`` (copies of their state and inputs), to run later
        or elsewhere (:class:`~magctl.core.kernel.EventRequest`)."""
        lf = self.schedule.leaves[i]
        arrays, inputs = self._event_arrays(buf, batch, i, rows)
        sub = unpack_state(lf.block, [a[rows] for a in arrays], state["leaves"][i], self.vars[i])
        return EventRequest(lf.block, rows.copy(), sub, inputs, tick)

    def merge_event(self, buf: dict, batch: int, i: int, request: EventRequest, result: dict) -> None:
        """Leaf ``i``'s event result merged into the compiled buffers (:func:`~magctl.core.kernel.merge_event`)."""
        arrays = self._event_arrays(buf, batch, i, request.rows)[0]
        merge_event(request.block, arrays, request.rows, request.state, result, self.events[i], self.vars[i])

    def outputs_of(self, buf: dict, batch: int, i: int) -> dict[str, np.ndarray]:
        lf = self.schedule.leaves[i]
        out = {}
        for p, port in lf.block.outputs.items():
            s = self.out_slots[i][p]
            out[p] = buf["O"][s.group][batch * s.offset:batch * (s.offset + s.width)].reshape(
                (batch, *port.shape)).copy()
        return out

    # --- running --------------------------------------------------------------------------------
    def run(self, state: dict, ext: dict[str, np.ndarray], steps: int, batch: int, record: list[str]):
        """``steps`` ticks from ``state`` with the diagram inputs ``ext`` (each ``(B, T, *shape)``).

        Returns the record arrays by name (``(B, T, *shape)``, views of one contiguous array per dtype), the
        final diagram state, and whether every recorded float is finite (one pass over the contiguous
        float record: a strided pass per signal costs several times more).
        """
        sched = self.schedule
        buf = self._buffers(state, batch)
        noise = self._noise(state, batch)
        rec_off = np.full(len(self.record_names), -1, dtype=np.int64)
        width = {g: 0 for g in GROUPS.values()}
        where = {}
        for name in record:
            i, p = self._leaf_port(name)
            slot = self.out_slots[i][p]
            rec_off[self.record_names.index(name)] = width[slot.group]
            where[name] = (slot.group, width[slot.group], slot.width, sched.leaves[i].block.outputs[p])
            width[slot.group] += slot.width
        recs = tuple(np.empty((batch, steps, width[g]), dtype=d)
                     for g, d in (("F", np.float64), ("I", np.int64), ("B", np.bool_)))
        by_group = dict(zip("FIB", recs, strict=True))
        ext_arrays = tuple(np.ascontiguousarray(np.asarray(ext[name], dtype=sched.inputs[name].dtype).reshape(
            batch, steps, -1)) for name in self.ext_slots)
        stop, rant = np.zeros(3, dtype=np.int64), np.zeros(len(sched.leaves), dtype=np.bool_)
        b0 = k0 = 0
        args = (steps, int(state["tick"]), ext_arrays, rec_off, *recs, self.param_tuples,
                *self._args(buf, batch, noise))
        while self.module().run_steps(b0, k0, stop, rant, *args):
            b0, k0, leaf = (int(x) for x in stop)
            self.handle_events(buf, state, batch, leaf, np.array([b0]))
        held = list(state["held"])
        for i in self.multirate:
            held[i] = self.outputs_of(buf, batch, i)
        final = {"tick": int(state["tick"]) + steps, "leaves": self._unpack(buf, state, batch), "held": held}
        out = {name: by_group[g][:, :, off:off + w].reshape((batch, steps, *port.shape))
               for name, (g, off, w, port) in where.items()}
        finite = bool(np.isfinite(recs[0].sum())) if recs[0].size else True
        return out, final, finite

    def stepper(self, state: dict, batch: int) -> Stepper:
        """The diagram stepped one tick per call from ``state`` (the rig's form)."""
        return Stepper(self, state, batch)


class Stepper:
    """One compiled tick per call, the state held in the compiled buffers (the rig's controller).

    ``step(u)`` takes the diagram inputs (``(B, *shape)`` or one trial's value) and returns the
    exported outputs as views of the engine's buffers: valid until the next step (copy what is kept).
    ``state`` gives the diagram state as the interpreted engine holds it.

    Python events are handled at the end of the tick that raised them, as in :meth:`CompiledDiagram.run`,
    unless :attr:`defer` is set: then the stepper calls ``defer(request)`` with an
    :class:`~magctl.core.kernel.EventRequest` for the trials whose flag rose in the tick and leaves the flags up
    (the events are pending: a trial's flag stays up, and is not requested again, until its result is
    applied); :meth:`apply_event` merges a result in before any later tick. The rig runs its planners this
    way, off the tick (docs/rig.md "Planning off the frame").
    """

    def __init__(self, compiled: CompiledDiagram, state: dict, batch: int):
        self.compiled, self.batch = compiled, int(batch)
        self._like = state
        self._buf = compiled._buffers(state, self.batch)
        self._tick = int(state["tick"])
        self._args = compiled._args(self._buf, self.batch, compiled._noise(state, self.batch))
        self._fn = compiled.module().step_once
        sched, b = compiled.schedule, self.batch

        def view(bufs: dict, slot: _Slot, shape: tuple) -> np.ndarray:
            return bufs[slot.group][b * slot.offset:b * (slot.offset + slot.width)].reshape((b, *shape))

        self.inputs = {name: view(self._buf["X"], slot, sched.inputs[name].shape)
                       for name, slot in compiled.ext_slots.items()}
        """The diagram inputs of the next step, as views of the engine's buffers: a caller may write them in
        place and call :meth:`step_in_place` (the rig's controller does, saving a copy per input)."""
        self._in = list(self.inputs.items())
        self._out = {name: view(self._buf["O"], compiled.out_slots[i][p], sched.leaves[i].block.outputs[p].shape)
                     for name, (i, p) in sched.outputs.items()}
        self._flags = [(i, self._buf["S"][s.group][b * s.offset:b * (s.offset + 1)])
                       for i, s in ((i, compiled.state_slots[i][v]) for i, v in compiled.events.items())]
        self.defer = None
        """None, or the callable given each :class:`~magctl.core.kernel.EventRequest` instead of handling it."""
        self._pending = {i: np.zeros(b, dtype=bool) for i in compiled.events}

    def step(self, u: dict | None = None) -> dict[str, np.ndarray]:
        """One tick with the diagram inputs ``u`` (each ``(B, *shape)`` or one trial's value)."""
        u = u or {}
        for name, target in self._in:
            try:
                target[...] = u[name]
            except KeyError:
                raise MagctlError(f"compiled step: diagram input {name!r} needs a value") from None
            except ValueError as err:
                raise MagctlError(f"compiled step: diagram input {name!r}: {err}") from None
        return self.step_in_place()

    def step_in_place(self) -> dict[str, np.ndarray]:
        """One tick with the inputs as written into :attr:`inputs`."""
        self._fn(self._tick, *self._args)
        self._tick += 1
        for i, flags in self._flags:      # events of every trial at this tick, handled before the next one
            if flags.any():
                if self.defer is None:
                    self.compiled.handle_events(self._buf, self._like, self.batch, i, np.flatnonzero(flags))
                    continue
                pending = self._pending[i]
                rows = np.flatnonzero(flags & ~pending)
                if rows.size:
                    pending[rows] = True
                    self.defer(self.compiled.event_request(self._buf, self._like, self.batch, i, rows,
                                                           self._tick - 1))
        return dict(self._out)

    def apply_event(self, request: EventRequest, result: dict) -> None:
        """Merge a deferred event's result (``request.run()``) into the state before the next tick: the elements
        the handler changed take its values, the rest keep what the ticks since the request gave them
        (:func:`~magctl.core.kernel.merge_event`); the flag is cleared and the rows may raise it again."""
        i = next(i for i in self._pending if self.compiled.schedule.leaves[i].block is request.block)
        self.compiled.merge_event(self._buf, self.batch, i, request, result)
        self._pending[i][request.rows] = False

    @property
    def state(self) -> dict:
        """The diagram state after the last step, as the interpreted engine holds it."""
        c = self.compiled
        held = list(self._like["held"])
        for i in c.multirate:
            held[i] = c.outputs_of(self._buf, self.batch, i)
        return {"tick": self._tick, "leaves": c._unpack(self._buf, self._like, self.batch), "held": held}


def _guarded(cond: str, lines: list[str]) -> list[str]:
    if cond == "True":
        return [x for line in lines for x in line.split("\n")]
    return [f"if {cond}:"] + _indent([x for line in lines for x in line.split("\n")], 1)


def _indent(lines: list[str], level: int) -> list[str]:
    pad = "    " * level
    return [pad + line for line in lines]


def compile_diagram(diagram) -> CompiledDiagram:
    """``diagram`` compiled (raises :class:`NotCompilable`, naming the block, when a leaf has no kernel)."""
    cached = getattr(diagram, "_compiled", None)
    if cached is None:
        cached = CompiledDiagram(diagram)
        diagram._compiled = cached
    return cached
