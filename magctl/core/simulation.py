"""Batched, deterministic simulation of a diagram.

The step itself is the diagram's :meth:`~magctl.core.schedule.Schedule.run`, the
same routine behind ``Diagram.step`` and the rig; this module adds the batch,
the input arrays, recording and the finite-value checks.

``simulate(diagram, steps, batch=B, seed=S)`` steps B trials in lockstep and
records every leaf output as an array shaped ``(B, T, …)``. Trial ``k``'s
random streams come from ``SeedSequence(S, spawn_key=(k, …))`` so its
trajectory is the same in any batch and any process (pass ``trials=`` to run
a slice of a larger experiment).
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from magctl.core.block import as_batch
from magctl.core.checks import check_whole
from magctl.core.diagram import Diagram
from magctl.core.errors import NonFiniteSignalError, ParameterError, WiringError
from magctl.core.random import check_seed

ENGINES = ("interpreted", "compiled", "auto")


@dataclass
class SimResult:
    """Result of :func:`simulate`.

    Attributes
    ----------
    t : ndarray, shape (T,)
        Time of each step in seconds.
    signals : dict of str to ndarray
        Recorded signals ``"block.port"`` (nested blocks as ``"outer/inner.port"``),
        each shaped ``(B, T, *port.shape)``.
    outputs : dict of str to ndarray
        The diagram's exported outputs, same layout. ``t, y = result`` unpacks these.
    final_state : dict
        Diagram state after the last step (continue with ``simulate(..., state=)``).
    trials : list of int
        Global trial indices of the batch rows.
    inputs : dict of str to ndarray
        The diagram's exported inputs as applied, each ``(B, T, *port.shape)``.
    name : str
        Name of the simulated diagram.
    units : dict of str to str
        Unit of each exported output and input port (``"m"``, ``"m/s"`` …).

    Notes
    -----
    magctl's arrays are trial-major, ``(B, T, …)``, so a batch slices like a numpy array of
    trajectories. python-control orders a response the other way round, signal × trace × time;
    :meth:`to_control` converts, and :meth:`to_xarray` labels the axes.
    """

    t: np.ndarray
    signals: dict[str, np.ndarray] = field(repr=False)
    outputs: dict[str, np.ndarray] = field(repr=False)
    final_state: dict = field(repr=False)
    trials: list[int] = field(default_factory=list, repr=False)
    inputs: dict[str, np.ndarray] = field(default_factory=dict, repr=False)
    name: str = ""
    units: dict[str, str] = field(default_factory=dict, repr=False)

    def __repr__(self) -> str:
        b = len(self.trials) if self.trials else (next(iter(self.outputs.values())).shape[0] if self.outputs else 0)
        dt = f" of {self.t[1] - self.t[0]:.4g} s" if len(self.t) > 1 else ""
        outs = ", ".join(f"{k} {tuple(v.shape[2:])}" for k, v in self.outputs.items())
        return (f"<SimResult {self.name or 'diagram'}: {b} trials × {len(self.t)} steps{dt}; "
                f"outputs: {outs or 'none'}; {len(self.signals)} recorded signals>")

    def __iter__(self):
        return iter((self.t, self.outputs))

    @staticmethod
    def _channels(arrays: dict[str, np.ndarray]) -> tuple[list[str], np.ndarray | None]:
        """Real-valued signals flattened to channels: labels ``name`` / ``name[i]`` and ``(n, B, T)`` data."""
        labels, data = [], []
        for name, arr in arrays.items():
            if np.dtype(arr.dtype).kind not in "fiu":
                continue  # flags are not signals of a response
            b, t = arr.shape[:2]
            flat = np.asarray(arr, dtype=float).reshape(b, t, -1)
            n = flat.shape[2]
            labels += [f"{name}[{e}]" for e in range(n)] if arr.ndim > 2 else [name]
            data.append(np.moveaxis(flat, 2, 0))
        return labels, (np.concatenate(data, axis=0) if data else None)

    def to_control(self, trial: int | None = None):
        """The exported outputs (and inputs) as a python-control ``TimeResponseData``.

        Parameters
        ----------
        trial : int, optional
            Row of the batch to convert (a single trace); default: every trial as one trace each.

        Returns
        -------
        control.TimeResponseData
            python-control's axis order: ``outputs`` is ``(n_outputs, n_traces, T)`` (``(n_outputs,
            T)`` for one trial), channels named ``name`` or ``name[i]`` for vector ports — the same
            labels as ``Diagram.linearize`` gives its outputs. Boolean ports are left out.
        """
        import control

        outs = self.outputs
        ins = self.inputs
        if trial is not None:
            b = next(iter(outs.values())).shape[0] if outs else 0
            if not -b <= int(trial) < b:
                raise IndexError(f"trial {trial} out of range for a batch of {b}")
            outs = {k: v[[int(trial)]] for k, v in outs.items()}
            ins = {k: v[[int(trial)]] for k, v in ins.items()}
        out_labels, y = self._channels(outs)
        in_labels, u = self._channels(ins)
        if y is None:
            raise ValueError(f"simulation of {self.name!r} has no real-valued output to convert")
        multi = trial is None
        if not multi:
            y = y[:, 0]
            u = None if u is None else u[:, 0]
        trace_labels = [f"trial {k}" for k in self.trials] if multi and self.trials else None
        return control.TimeResponseData(
            self.t, y, inputs=u, output_labels=out_labels, input_labels=in_labels or None, multi_trace=multi,
            trace_labels=trace_labels, trace_types=["forced"] * y.shape[1] if multi else None,
            sysname=self.name or None, plot_inputs=u is not None,
            issiso=y.shape[0] == 1 and (u is None or u.shape[0] == 1))

    def to_xarray(self, signals: bool = False):
        """The outputs (and, with ``signals=True``, every recorded signal) as an ``xarray.Dataset``.

        Dimensions ``trial`` (the global trial indices), ``time`` (s) and one per port axis
        (``<name>_dim0`` …); needs the optional ``xarray`` extra (``pip install 'magctl[xarray]'``).
        """
        try:
            import xarray as xr
        except ImportError:
            raise ImportError("SimResult.to_xarray needs xarray: pip install 'magctl[xarray]'") from None
        arrays = dict(self.outputs)
        if signals:
            arrays |= {k: v for k, v in self.signals.items() if k not in arrays}
        b = next(iter(arrays.values())).shape[0] if arrays else 0
        trials = self.trials or list(range(b))
        data = {}
        for name, arr in arrays.items():
            dims = ("trial", "time", *(f"{name}_dim{d}" for d in range(arr.ndim - 2)))
            # a last axis of two is a vector in the plane of the slide: label its components
            coords = {dims[-1]: ["x", "y"]} if arr.ndim > 2 and arr.shape[-1] == 2 else None
            attrs = {"units": self.units[name]} if name in self.units else {}
            data[name] = xr.DataArray(arr, dims=dims, coords=coords, attrs=attrs)
        ds = xr.Dataset(data, coords={"trial": trials, "time": self.t}, attrs={"diagram": self.name})
        ds["time"].attrs["units"] = "s"
        return ds

    def plot(self, names=None, trial: int | None = None):
        """The exported outputs against time: one panel per real-valued channel (``name`` or ``name[i]``, with its
        unit), one line per trial (``trial`` to draw one row of the batch). Returns the matplotlib ``Figure``."""
        import matplotlib.pyplot as plt

        outs = {k: v for k, v in self.outputs.items() if names is None or k in names}
        if trial is not None:
            outs = {k: v[[int(trial)]] for k, v in outs.items()}
        labels, y = self._channels(outs)
        if y is None:
            raise ValueError(f"simulation of {self.name!r} has no real-valued output to plot")
        fig, axes = plt.subplots(len(labels), 1, sharex=True, squeeze=False, figsize=(6.4, 1.2 + 1.6 * len(labels)))
        rows = self.trials or list(range(y.shape[1]))
        for ax, label, data in zip(axes[:, 0], labels, y, strict=True):
            unit = self.units.get(label.split("[")[0], "")
            for k, trace in enumerate(data):
                ax.plot(self.t, trace, lw=1, label=f"trial {rows[k] if trial is None else trial}")
            ax.set_ylabel(f"{label} ({unit})" if unit and unit != "1" else label)
            ax.grid(alpha=0.3)
        axes[-1, 0].set_xlabel("time (s)")
        axes[0, 0].set_title(self.name or "simulation", fontsize=10)
        if y.shape[1] <= 8:
            axes[0, 0].legend(fontsize=7)
        return fig

    def __getitem__(self, name: str) -> np.ndarray:
        if name in self.outputs:
            return self.outputs[name]
        try:
            return self.signals[name]
        except KeyError:
            known = sorted(self.outputs) + sorted(self.signals)
            raise KeyError(f"no recorded signal {name!r}; recorded: {known}") from None


def _external_values(diagram: Diagram, inputs: Mapping | None, batch: int, steps: int):
    """Per-step values of the diagram's exported inputs as ``(B, T, *shape)`` arrays."""
    inputs = dict(inputs or {})
    unknown = set(inputs) - set(diagram.inputs)
    if unknown:
        raise WiringError(f"diagram {diagram.name!r} has no inputs {sorted(unknown)}; inputs: {sorted(diagram.inputs)}")
    values = {}
    for name, p in diagram.inputs.items():
        if name not in inputs:
            raise WiringError(f"diagram input {diagram.name}.{name} needs a value: pass inputs={{{name!r}: …}}")
        v = np.asarray(inputs[name], dtype=p.dtype)
        for shape in ((batch, steps, *p.shape), (steps, *p.shape)):
            if v.shape == shape:
                values[name] = np.broadcast_to(v, (batch, steps, *p.shape))
                break
        else:
            const = as_batch(v, p, batch)
            values[name] = np.broadcast_to(const[:, None], (batch, steps, *p.shape))
    return values


def simulate(
    diagram: Diagram,
    steps: int,
    *,
    batch: int = 1,
    seed: int = 0,
    inputs: Mapping | None = None,
    record: Iterable[str] | None = None,
    trials: Sequence[int] | None = None,
    state: dict | None = None,
    check_finite: bool = True,
    check_every: int = 64,
    engine: str | None = None,
) -> SimResult:
    """Simulate ``batch`` trials of ``diagram`` for ``steps`` base periods.

    Parameters
    ----------
    diagram : Diagram
        The system to run.
    steps : int
        Number of base-period steps.
    batch : int
        Number of trials stepped in lockstep.
    seed : int
        Root seed; trial ``k`` uses ``SeedSequence(seed, spawn_key=(k, …))``.
    inputs : mapping
        Values of the diagram's exported inputs: constants, ``(T, …)`` or ``(B, T, …)``.
    record : iterable of str, optional
        Leaf outputs to record (``"block.port"``); all of them by default. Exported
        outputs are always recorded.
    trials : sequence of int, optional
        Global indices of the trials in this batch (default ``0 … B−1``).
    state : dict, optional
        Start from this diagram state instead of the initial one.
    check_finite : bool
        Scan recorded signals for NaN/inf every ``check_every`` steps and raise
        :class:`NonFiniteSignalError` naming the producing block and port, the
        consuming inputs and the first step; ``partial`` holds what ran before.
    engine : {"interpreted", "compiled", "auto"}, optional
        ``"compiled"`` runs the diagram's generated, numba-compiled loop (:mod:`magctl.core.compiled`;
        every leaf needs a kernel, else :class:`~magctl.core.compiled.NotCompilable` names the block);
        ``"auto"`` does so when it can and interprets otherwise. Same results either way (to
        floating-point reassociation), trial by trial. A compiled run scans for non-finite values once,
        after its last step. Default: ``$MAGCTL_ENGINE``, else ``"interpreted"``.
    """
    if engine is None:
        engine = os.environ.get("MAGCTL_ENGINE") or "interpreted"
    if engine not in ENGINES:
        raise ValueError(f"engine {engine!r} is not one of {', '.join(ENGINES)}")
    sched = diagram.schedule
    steps = check_whole("simulate: steps", steps, 0, error=ParameterError)
    batch = check_whole("simulate: batch", batch, 1, error=ParameterError)
    if seed is not None:
        seed = check_seed(seed)
    trials = list(range(batch)) if trials is None else list(trials)
    if len(trials) != batch:
        raise ValueError(f"got {len(trials)} trial indices for a batch of {batch}")
    st = sched.initial_state(batch, seed=seed, trials=trials) if state is None else state
    ext = _external_values(diagram, inputs, batch, steps)

    names = sched.signal_names()
    wanted = None if record is None else set(record)
    exported_refs = {f"{sched.leaves[i].path}.{p}" for i, p in sched.outputs.values()}
    if wanted is not None:
        known = {n for _, _, n in names}
        missing = wanted - known
        if missing:
            raise WiringError(f"cannot record unknown signals {sorted(missing)}")
        wanted |= exported_refs
    rec_specs = [(i, p, n) for i, p, n in names if wanted is None or n in wanted]
    if engine != "interpreted":
        from magctl.core.compiled import NotCompilable, compile_diagram

        try:
            compiled = compile_diagram(diagram)
        except NotCompilable:
            if engine == "compiled":
                raise
        else:
            buffers, final, finite = compiled.run(st, ext, steps, batch, [n for _, _, n in rec_specs])
            if check_finite and not finite:
                plan = [(i, p, buffers[n]) for i, p, n in rec_specs]
                _check_finite(sched, plan, 0, steps, tick0_of(st), diagram, buffers, trials, final["leaves"],
                              final["held"])
            return _result(diagram, buffers, steps, tick0_of(st), final, trials, ext)
    ports = {n: sched.leaves[i].block.outputs[p] for i, p, n in rec_specs}
    buffers = {n: np.empty((batch, steps, *pt.shape), dtype=pt.dtype) for n, pt in ports.items()}
    rec_plan = [(i, p, buffers[n]) for i, p, n in rec_specs]

    leaf_states = list(st["leaves"])
    held = list(st["held"])
    tick0 = st["tick"]
    run = sched.run
    ext_items = list(ext.items())
    last_checked = 0

    for k in range(steps):
        outs = run(tick0 + k, {name: v[:, k] for name, v in ext_items}, leaf_states, held)
        for i, p, buf in rec_plan:
            buf[:, k] = outs[i][p]
        if check_finite and (k + 1 - last_checked >= check_every or k == steps - 1):
            _check_finite(sched, rec_plan, last_checked, k + 1, tick0, diagram, buffers, trials, leaf_states, held)
            last_checked = k + 1

    final = {"tick": tick0 + steps, "leaves": leaf_states, "held": held}
    return _result(diagram, buffers, steps, tick0, final, trials, ext)


def tick0_of(state: dict) -> int:
    return int(state["tick"])


def _result(diagram, buffers, steps, tick0, final, trials, inputs=None) -> SimResult:
    sched = diagram.schedule
    t = (tick0 + np.arange(steps)) * diagram.dt
    outputs = {name: buffers[f"{sched.leaves[i].path}.{p}"] for name, (i, p) in sched.outputs.items()}
    applied = {k: v[:, :steps] for k, v in (inputs or {}).items()}
    units = {name: p.unit for name, p in (diagram.inputs | diagram.outputs).items()}
    return SimResult(t, buffers, outputs, final, list(trials), applied, diagram.name, units)


def _check_finite(sched, rec_plan, k0, k1, tick0, diagram, buffers, trials, leaf_states, held):
    if all(buf.dtype.kind != "f" or np.isfinite(buf[:, k0:k1].sum()) for _, _, buf in rec_plan):
        return  # a finite sum: every value is finite (the common case, in one pass per signal)
    first = None
    for i, p, buf in rec_plan:
        seg = buf[:, k0:k1]
        if seg.dtype.kind != "f":
            continue
        bad = ~np.isfinite(seg.reshape(seg.shape[0], seg.shape[1], -1)).all(axis=2)
        if bad.any():
            step = int(np.argmax(bad.any(axis=0)))
            if first is None or (step, i) < first[:2]:
                first = (step, i, p, np.flatnonzero(bad[:, step]))
    if first is None:
        return
    step, i, p, rows = first
    partial_len = k0 + step
    partial = _result(
        diagram,
        {n: b[:, :partial_len] for n, b in buffers.items()},
        partial_len,
        tick0,
        {"tick": tick0 + k1, "leaves": leaf_states, "held": held},
        trials,
    )
    raise NonFiniteSignalError(
        step=tick0 + partial_len,
        source=f"{sched.leaves[i].path}.{p}",
        consumers=sched.consumers(i, p),
        trials=[trials[r] for r in rows],
        partial=partial,
    )
