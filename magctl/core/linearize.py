"""Diagrams as python-control systems: exact export of linear diagrams, and
linearisation of nonlinear ones about an operating point.

Every leaf becomes a ``control.StateSpace`` whose signals are named after the
leaf output that drives them, and ``control.interconnect`` joins them by
name. Linear leaves export exactly (``to_control``); a nonlinear leaf uses its
own ``jacobians(state, u)`` if it has one (exact, e.g. from casadi) and central
finite differences of ``step`` otherwise, over the leaf's declared real state
(:attr:`magctl.core.block.StateVar.real`). The exported system's states are
named ``"leafpath.name[i]"`` (nested diagrams as ``"outer/inner.name[i]"``).

Only real-valued (float) signals are part of a linear model: boolean and
integer ports (flags, status codes) are left out of every leaf model and of
the exported inputs and outputs, and a leaf input driven by such a port is
an error only if it is a float input.

The functions read a diagram's schedule (:mod:`magctl.core.schedule`) and do not import
:mod:`magctl.core.diagram`, whose ``Diagram.to_control()`` and ``Diagram.linearize()`` call them.
"""

from __future__ import annotations

import control
import numpy as np

from magctl.core.block import STREAM, SUBSTATE, Block, flat_state_vars, state_get, state_with
from magctl.core.errors import MagctlError, NotLinearError, WiringError
from magctl.core.schedule import EXTERNAL


def _real(port) -> bool:
    return np.dtype(port.dtype).kind == "f"


def _signal_names(tag: str, shape) -> list[str]:
    n = int(np.prod(shape, dtype=int))
    return [f"{tag}_{e}" for e in range(n)]


def _labels(name: str, shape) -> list[str]:
    n = int(np.prod(shape, dtype=int))
    return [f"{name}[{e}]" for e in range(n)] if shape else [name]


def _state_labels(block: Block, sys, path: str) -> list[str]:
    """Names of a leaf model's states: its own labels when it set them, else the block's declared real state."""
    own = list(getattr(sys, "state_labels", []) or [])
    if own and not all(lbl.startswith("x[") for lbl in own):
        return [f"{path}.{lbl}" for lbl in own]
    declared = [lbl for keys, v in _real_entries(block) for lbl in v.labels(path, keys)]
    if len(declared) == sys.nstates:
        return declared
    return [f"{path}.x[{e}]" for e in range(sys.nstates)]


def _interconnect(diagram, systems: list, state_names: list[list[str]]) -> control.StateSpace:
    sched = diagram.schedule
    if sched.multirate:
        raise WiringError(f"diagram {diagram.name!r} mixes sample periods; export needs a single rate")
    out_tag = {(i, p): f"s{i}_{p}" for i, lf in enumerate(sched.leaves) for p in lf.block.outputs}
    named = []
    for i, (lf, sys) in enumerate(zip(sched.leaves, systems, strict=True)):
        in_names = []
        for p, j, q in lf.wiring:
            if not _real(lf.block.inputs[p]):
                continue  # flags are not part of a linear model
            tag = f"in_{q}" if j == EXTERNAL else out_tag[(j, q)]
            in_names += _signal_names(tag, lf.block.inputs[p].shape)
        out_names = [
            n for p, port in lf.block.outputs.items() if _real(port)
            for n in _signal_names(out_tag[(i, p)], port.shape)
        ]
        if sys.ninputs != len(in_names) or sys.noutputs != len(out_names):
            raise WiringError(
                f"block {lf.path!r}: its linear model has {sys.ninputs} inputs/{sys.noutputs} outputs, "
                f"its real-valued ports {len(in_names)}/{len(out_names)}"
            )
        named.append(control.ss(sys.A, sys.B, sys.C, sys.D, dt=diagram.dt, inputs=in_names, outputs=out_names,
                                name=f"s{i}"))
    ins = [(name, p) for name, p in diagram.inputs.items() if _real(p)]
    outs = [(name, i, p) for name, (i, p) in sched.outputs.items() if _real(sched.leaves[i].block.outputs[p])]
    inplist = [n for name, p in ins for n in _signal_names(f"in_{name}", p.shape)]
    outlist = [n for name, i, p in outs for n in _signal_names(out_tag[(i, p)], sched.leaves[i].block.outputs[p].shape)]
    in_labels = [lbl for name, p in ins for lbl in _labels(name, p.shape)]
    out_labels = [lbl for name, i, p in outs for lbl in _labels(name, sched.leaves[i].block.outputs[p].shape)]
    if not outlist:
        raise MagctlError(f"diagram {diagram.name!r} exports no real-valued output: nothing to linearise")
    sys = control.interconnect(named, inplist=inplist, outlist=outlist, dt=diagram.dt, check_unused=False,
                               name=diagram.name)
    states = [lbl for names in state_names for lbl in names]
    return control.ss(sys.A, sys.B, sys.C, sys.D, dt=diagram.dt, inputs=in_labels, outputs=out_labels,
                      states=states, name=diagram.name)


def diagram_to_control(diagram) -> control.StateSpace:
    """Exact python-control model of a diagram whose leaves are all linear.

    States are named ``"leafpath.state[i]"``; boolean and integer ports are left out.
    """
    systems, names = [], []
    for lf in diagram.schedule.leaves:
        try:
            sys = control.ss(lf.block.to_control())
        except NotLinearError as err:
            raise NotLinearError(
                f"diagram {diagram.name!r} is not linear: {err}; use diagram.linearize(state, u)"
            ) from None
        systems.append(sys)
        names.append(_state_labels(lf.block, sys, lf.path))
    return _interconnect(diagram, systems, names)


# ------------------------------------------------------------------------------------------------
# finite differences over declared state


def trial_zero(block: Block, state: dict, path: str = "") -> dict:
    """Trial 0 of a leaf state, with its random streams switched off (``None``).

    Entries are checked against the block's declaration (nested ones included); an
    undeclared or missing entry or a wrong shape raises a :class:`MagctlError` naming
    the block and the entry.
    """
    where = path or block.name

    def walk(st, variables, prefix):
        if not isinstance(st, dict):
            raise MagctlError(f"block {where!r}: state {'.'.join(prefix) or ''} must be a dict, "
                              f"got {type(st).__name__}")
        undeclared = sorted(set(st) - {v.name for v in variables})
        if undeclared:
            raise MagctlError(f"block {where!r} ({type(block).__name__}): state entries "
                              f"{['.'.join((*prefix, k)) for k in undeclared]} are not declared in state_vars(), "
                              f"so a linearisation cannot walk them")
        out = dict(st)
        for v in variables:
            key = ".".join((*prefix, v.name))
            if v.name not in st:
                raise MagctlError(f"block {where!r}: state has no entry {key!r} (entries: {sorted(st)})")
            val = st[v.name]
            if v.dtype == SUBSTATE:
                out[v.name] = walk(val, v.sub, (*prefix, v.name))
            elif v.dtype == STREAM:
                out[v.name] = None
            elif v.batched:
                arr = np.asarray(val)
                if arr.shape[1:] != v.shape or arr.shape[0] < 1:
                    raise MagctlError(f"block {where!r}: state entry {key!r} has shape {arr.shape}, "
                                      f"declared (B, {', '.join(map(str, v.shape))})")
                out[v.name] = arr[:1]
        return out

    return walk(state, block.state_vars(), ())


def _real_entries(block: Block):
    return [(keys, v) for keys, v in flat_state_vars(block.state_vars()) if v.real]


def _flat(state: dict, entries) -> np.ndarray:
    if not entries:
        return np.zeros(0)
    return np.concatenate([np.asarray(state_get(state, keys), dtype=float)[0].ravel() for keys, _ in entries])


def _with(state: dict, entries, x: np.ndarray) -> dict:
    pos = 0
    for keys, v in entries:
        state = state_with(state, keys, x[pos:pos + v.size].reshape((1, *v.shape)).copy())
        pos += v.size
    return state


def finite_difference_jacobians(block: Block, state: dict, u: dict, eps: float = 1e-6):
    """(A, B, C, D) of a block at ``(state, u)`` for trial 0, by central differences of ``block.step``
    (two step sizes, Richardson-extrapolated: error O(h⁴)).

    The state vector is the block's declared real state (:meth:`~magctl.core.block.Block.state_vars`,
    entries with :attr:`~magctl.core.block.StateVar.real`) in declaration order; other entries are
    held at their values in ``state``. Inputs and outputs are the real-valued ports in declaration
    order; boolean inputs are held at their values in ``u``.
    """
    real_vars = _real_entries(block)
    x0 = _flat(state, real_vars)
    in_ports = [p for p in block.inputs.values() if _real(p)]
    out_ports = [p for p in block.outputs.values() if _real(p)]
    u0 = (np.concatenate([np.asarray(u[p.name], dtype=float)[0].ravel() for p in in_ports])
          if in_ports else np.zeros(0))

    def evaluate(x, uv):
        st = _with(state, real_vars, x)
        ui, pos = dict(u), 0
        for p in in_ports:
            ui[p.name] = uv[pos:pos + p.size].reshape((1, *p.shape))
            pos += p.size
        y, nxt = block.step(st, ui)
        yv = (np.concatenate([np.asarray(y[p.name], dtype=float)[0].ravel() for p in out_ports])
              if out_ports else np.zeros(0))
        return _flat(nxt, real_vars), yv

    xn0, y0 = evaluate(x0, u0)
    nx, nu, ny = x0.size, u0.size, y0.size

    def central(shift, h):
        (xp, yp), (xm, ym) = shift(h), shift(-h)
        return (xp - xm) / (2 * h), (yp - ym) / (2 * h)

    def derivative(shift, h):
        # Richardson extrapolation of two central differences, (4 D(h/2) − D(h)) / 3: the O(h²) error
        # cancels. magctl's signals are in SI, so the step (≥ eps) can be a sizeable fraction of the scale
        # on which a law is nonlinear (a heading atan2(e_y, e_x) at e_x = 100 µm bends over 1e-6 m)
        (fx1, fy1), (fx2, fy2) = central(shift, h), central(shift, h / 2)
        return (4 * fx2 - fx1) / 3, (4 * fy2 - fy1) / 3

    A, B = np.zeros((nx, nx)), np.zeros((nx, nu))
    C, D = np.zeros((ny, nx)), np.zeros((ny, nu))
    for j in range(nx):
        e = np.zeros(nx)
        e[j] = 1.0
        A[:, j], C[:, j] = derivative(lambda h, e=e: evaluate(x0 + h * e, u0), eps * max(1.0, abs(x0[j])))
    for j in range(nu):
        e = np.zeros(nu)
        e[j] = 1.0
        B[:, j], D[:, j] = derivative(lambda h, e=e: evaluate(x0, u0 + h * e), eps * max(1.0, abs(u0[j])))
    return A, B, C, D


def _operating_inputs(diagram, u) -> dict:
    """The diagram inputs for trial 0 as ``(1, *shape)`` arrays, or a clear error."""
    given = dict(u or {})
    unknown = sorted(set(given) - set(diagram.inputs))
    if unknown:
        raise MagctlError(f"diagram {diagram.name!r} has no inputs {unknown}; inputs: {sorted(diagram.inputs)}")
    missing = sorted(set(diagram.inputs) - set(given))
    if missing:
        raise MagctlError(f"linearize diagram {diagram.name!r}: no operating value for inputs {missing}; "
                          f"pass u={{name: value}} for every input")
    out = {}
    for k, p in diagram.inputs.items():
        arr = np.asarray(given[k], dtype=p.dtype)
        if arr.shape == (*p.shape,) or arr.shape == (1, *p.shape):
            out[k] = arr.reshape((1, *p.shape))
        elif arr.ndim == len(p.shape) + 1 and arr.shape[1:] == p.shape:
            out[k] = arr[:1]
        else:
            raise MagctlError(f"linearize diagram {diagram.name!r}: input {k!r} has shape {arr.shape}, "
                              f"expected {p.shape} or (B, {', '.join(map(str, p.shape))})")
    return out


def linearize_diagram(diagram, state: dict, u: dict | None = None, eps: float = 1e-6):
    """Linearise ``diagram`` about ``state`` (a diagram state, trial 0 used) and inputs ``u``.

    The operating point is the noise-free path: every leaf's random stream is switched off
    (a block given ``rng=None`` draws no noise), so noise blocks pass their input and
    variability terms take their mean. Returns a discrete ``control.StateSpace`` with the
    diagram's ``dt`` whose states are the leaves' declared real states (exactly exported
    leaves: their own state), named ``"leafpath.name[i]"``, nested diagrams included.
    Boolean and integer ports are left out of the model.

    Raises
    ------
    MagctlError
        Missing or unknown inputs, a state that is not this diagram's, or a multirate diagram.
    """
    sched = diagram.schedule
    if not isinstance(state, dict) or not {"tick", "leaves", "held"} <= set(state):
        raise MagctlError(f"linearize diagram {diagram.name!r}: state must be a diagram state "
                          f"(from diagram.initial_state or a simulation's final_state)")
    if len(state["leaves"]) != len(sched.leaves):
        raise MagctlError(f"linearize diagram {diagram.name!r}: state has {len(state['leaves'])} leaf states, "
                          f"the diagram {len(sched.leaves)} leaves")
    if sched.multirate:
        raise MagctlError(f"diagram {diagram.name!r} mixes sample periods; linearisation needs a single rate")
    u = _operating_inputs(diagram, u)
    leaves = [trial_zero(lf.block, st, lf.path) for lf, st in zip(sched.leaves, state["leaves"], strict=True)]
    outs = sched.run(state["tick"], u, list(leaves), [None] * len(leaves), advance=False)
    systems, names = [], []
    for i, lf in enumerate(sched.leaves):
        blk, st = lf.block, leaves[i]
        try:
            sys = control.ss(blk.to_control())
        except NotLinearError:
            ui = sched.gather(i, outs, u)
            if hasattr(blk, "jacobians"):
                A, B, C, D = blk.jacobians(st, ui)
            else:
                A, B, C, D = finite_difference_jacobians(blk, st, ui, eps)
            sys = control.ss(A, B, C, D, dt=diagram.dt)
        systems.append(sys)
        names.append(_state_labels(blk, sys, lf.path))
    return _interconnect(diagram, systems, names)
