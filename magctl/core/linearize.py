"""Diagrams as python-control systems: exact export of linear diagrams, and
linearisation of nonlinear ones about an operating point.

Every leaf becomes a ``control.StateSpace`` whose signals are named after the
leaf output that drives them, and ``control.interconnect`` joins them by
name. Linear leaves export exactly (``to_control``); a nonlinear leaf uses its
own ``jacobians(state, u)`` if it has one (exact, e.g. from casadi) and central
finite differences of ``output``/``update`` otherwise.
"""

from __future__ import annotations

import copy

import control
import numpy as np

from magctl.core.diagram import EXTERNAL, Diagram
from magctl.core.errors import NotLinearError, WiringError


def _signal_names(tag: str, shape) -> list[str]:
    n = int(np.prod(shape, dtype=int))
    return [f"{tag}_{e}" for e in range(n)]


def _leaf_tags(diagram: Diagram):
    sched = diagram.schedule
    if sched.multirate:
        raise WiringError(f"diagram {diagram.name!r} mixes sample periods; export needs a single rate")
    out_tag = {}
    for i, lf in enumerate(sched.leaves):
        for p in lf.block.outputs:
            out_tag[(i, p)] = f"s{i}_{p}"
    return sched, out_tag


def _interconnect(diagram: Diagram, systems: list) -> control.StateSpace:
    sched, out_tag = _leaf_tags(diagram)
    named = []
    for i, (lf, sys) in enumerate(zip(sched.leaves, systems, strict=True)):
        in_names = []
        for p, j, q in lf.wiring:
            if lf.block.inputs[p].dtype == "bool":
                continue  # flags are not part of a linear model
            tag = f"in_{q}" if j == EXTERNAL else out_tag[(j, q)]
            in_names += _signal_names(tag, lf.block.inputs[p].shape)
        out_names = [
            n for p, port in lf.block.outputs.items() if port.dtype != "bool"
            for n in _signal_names(out_tag[(i, p)], port.shape)
        ]
        if sys.ninputs != len(in_names) or sys.noutputs != len(out_names):
            raise WiringError(
                f"block {lf.path!r}: its linear model has {sys.ninputs} inputs/{sys.noutputs} outputs, "
                f"its ports {len(in_names)}/{len(out_names)}"
            )
        named.append(control.ss(sys.A, sys.B, sys.C, sys.D, dt=diagram.dt, inputs=in_names, outputs=out_names,
                                name=f"s{i}"))
    inplist = [n for name, p in diagram.inputs.items() for n in _signal_names(f"in_{name}", p.shape)]
    outlist = [
        n for name, (i, p) in sched.outputs.items()
        for n in _signal_names(out_tag[(i, p)], sched.leaves[i].block.outputs[p].shape)
    ]
    out_labels = [
        f"{name}[{e}]" if sched.leaves[i].block.outputs[p].shape else name
        for name, (i, p) in sched.outputs.items()
        for e in range(int(np.prod(sched.leaves[i].block.outputs[p].shape, dtype=int)))
    ]
    in_labels = [
        f"{name}[{e}]" if p.shape else name
        for name, p in diagram.inputs.items()
        for e in range(int(np.prod(p.shape, dtype=int)))
    ]
    sys = control.interconnect(named, inplist=inplist, outlist=outlist, dt=diagram.dt, check_unused=False,
                               name=diagram.name)
    return control.ss(sys.A, sys.B, sys.C, sys.D, dt=diagram.dt, inputs=in_labels, outputs=out_labels,
                      name=diagram.name)


def diagram_to_control(diagram: Diagram) -> control.StateSpace:
    """Exact python-control model of a diagram whose leaves are all linear."""
    systems = []
    for lf in diagram.schedule.leaves:
        try:
            systems.append(control.ss(lf.block.to_control()))
        except NotLinearError as err:
            raise NotLinearError(
                f"diagram {diagram.name!r} is not linear: {err}; use diagram.linearize(state, u)"
            ) from None
    return _interconnect(diagram, systems)


# ------------------------------------------------------------------------------------------------


def _float_keys(state: dict) -> list[str]:
    return sorted(k for k, v in state.items() if isinstance(v, np.ndarray) and v.dtype.kind == "f")


def _flat(state: dict, keys: list[str]) -> np.ndarray:
    return np.concatenate([state[k][0].ravel() for k in keys]) if keys else np.zeros(0)


def _set_flat(state: dict, keys: list[str], x: np.ndarray) -> dict:
    new = copy.deepcopy(state)
    pos = 0
    for k in keys:
        n = new[k][0].size
        new[k] = new[k].copy()
        new[k][0] = x[pos:pos + n].reshape(new[k][0].shape)
        pos += n
    return new


def finite_difference_jacobians(block, state: dict, u: dict, eps: float = 1e-6):
    """(A, B, C, D) of a block at ``(state, u)`` for trial 0, by central differences.

    The state vector is the block's floating-point state arrays in key order.
    """
    keys = _float_keys(state)
    x0 = _flat(state, keys)
    in_ports = list(block.inputs.values())
    out_ports = list(block.outputs.values())
    u0 = np.concatenate([np.asarray(u[p.name], dtype=float)[0].ravel() for p in in_ports]) if in_ports else np.zeros(0)

    def evaluate(x, uv):
        st = _set_flat(state, keys, x)
        ui, pos = {}, 0
        for p in in_ports:
            ui[p.name] = uv[pos:pos + p.size].reshape((1, *p.shape))
            pos += p.size
        y = block.output(st, ui)
        yv = np.concatenate([np.asarray(y[p.name], dtype=float)[0].ravel() for p in out_ports if p.dtype != "bool"])
        nxt = block.update(copy.deepcopy(st), ui)
        return _flat(nxt, keys), yv

    xn0, y0 = evaluate(x0, u0)
    nx, nu, ny = x0.size, u0.size, y0.size
    A, B = np.zeros((nx, nx)), np.zeros((nx, nu))
    C, D = np.zeros((ny, nx)), np.zeros((ny, nu))
    for j in range(nx):
        h = eps * max(1.0, abs(x0[j]))
        dx = np.zeros(nx)
        dx[j] = h
        (xp, yp), (xm, ym) = evaluate(x0 + dx, u0), evaluate(x0 - dx, u0)
        A[:, j], C[:, j] = (xp - xm) / (2 * h), (yp - ym) / (2 * h)
    for j in range(nu):
        h = eps * max(1.0, abs(u0[j]))
        du = np.zeros(nu)
        du[j] = h
        (xp, yp), (xm, ym) = evaluate(x0, u0 + du), evaluate(x0, u0 - du)
        B[:, j], D[:, j] = (xp - xm) / (2 * h), (yp - ym) / (2 * h)
    return A, B, C, D


def linearize_diagram(diagram: Diagram, state: dict, u: dict | None = None, eps: float = 1e-6):
    """Linearise ``diagram`` about ``state`` (a diagram state, trial 0 used) and inputs ``u``.

    Returns a discrete ``control.StateSpace`` with the diagram's ``dt``. Boolean
    outputs (flags) are left out of nonlinear leaves' models, so their ports
    must not feed other leaves.
    """
    sched = diagram.schedule
    u = {k: np.asarray(v, dtype=float).reshape((1, *diagram.inputs[k].shape)) for k, v in (u or {}).items()}
    outs = sched.evaluate_outputs(state, u)
    systems = []
    for i, lf in enumerate(sched.leaves):
        blk, st = lf.block, state["leaves"][i]
        try:
            systems.append(control.ss(blk.to_control()))
            continue
        except NotLinearError:
            pass
        ui = sched.gather(i, outs, u)
        if hasattr(blk, "jacobians"):
            A, B, C, D = blk.jacobians(st, ui)
        else:
            A, B, C, D = finite_difference_jacobians(blk, st, ui, eps)
        systems.append(control.ss(A, B, C, D, dt=diagram.dt))
    return _interconnect(diagram, systems)
