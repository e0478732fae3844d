"""Diagrams: blocks wired by port name; a diagram is itself a block.

Wiring is validated when the diagram is built, and every error names the
block and port at fault: unknown names, an input with no driver or with two,
shape or unit mismatches, sample periods that are not multiples of the base
period, and algebraic loops (listing the cycle).

For execution a diagram is flattened into its leaf blocks (nested diagrams
dissolve, so nesting never invents an algebraic loop) and compiled into a
:class:`~magctl.core.schedule.Schedule`: leaves in feedthrough order, and for every leaf input the
leaf output (or diagram input) that drives it. The engines read that schedule and never this module:
:meth:`Diagram.compile`, :meth:`Diagram.to_control` and :meth:`Diagram.linearize` call them
(:mod:`magctl.core.compiled`, :mod:`magctl.core.linearize`).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence

import numpy as np

from magctl import FRAME_PERIOD_S
from magctl.core.block import Block, State, StateVar
from magctl.core.errors import RateError, WiringError
from magctl.core.ports import Port
from magctl.core.schedule import Schedule


def split_ref(ref: str) -> tuple[str, str]:
    """``"block.port"`` → ``("block", "port")``, with a clear error otherwise."""
    if not isinstance(ref, str) or ref.count(".") != 1:
        raise WiringError(f"signal reference {ref!r} must have the form 'block.port'")
    blk, prt = ref.split(".")
    return blk, prt


class Diagram(Block):
    """Blocks wired by port name; usable wherever a block is.

    Parameters
    ----------
    name : str
        Name of the diagram (as a block inside an enclosing diagram).
    blocks : sequence of Block
        Member blocks; names must be unique.
    connections : iterable of (str, str)
        ``("src.port", "dst.port")`` pairs.
    inputs : mapping of str to str or list of str
        Exported input name → the member input(s) it drives.
    outputs : mapping of str to str
        Exported output name → the member output it exposes.
    dt : float
        Base period; every member's period must be an integer multiple of it.

    Examples
    --------
    >>> from magctl.core.linear import Gain, Integrator
    >>> g = Gain("k", 2.0)
    >>> i = Integrator("int")
    >>> d = Diagram("loop", [g, i], [("k.y", "int.u")], inputs={"r": "k.u"}, outputs={"x": "int.y"})
    """

    def __init__(
        self,
        name: str,
        blocks: Sequence[Block],
        connections: Iterable[tuple[str, str]] = (),
        inputs: Mapping[str, str | Sequence[str]] | None = None,
        outputs: Mapping[str, str] | None = None,
        dt: float = FRAME_PERIOD_S,
    ):
        self.name = name  # set early: the port checks below name the diagram in their errors
        self.blocks: dict[str, Block] = {}
        for b in blocks:
            if not isinstance(b, Block):
                raise WiringError(f"diagram {name!r}: member {b!r} is not a Block")
            if b.name in self.blocks:
                raise WiringError(f"diagram {name!r} has two blocks named {b.name!r}")
            self.blocks[b.name] = b
        self.connections = [tuple(c) for c in connections]
        self.exported_inputs = {k: [v] if isinstance(v, str) else list(v) for k, v in (inputs or {}).items()}
        self.exported_outputs = dict(outputs or {})

        in_ports = [self._exported_input_port(k, refs) for k, refs in self.exported_inputs.items()]
        out_ports = [self._exported_output_port(k, ref) for k, ref in self.exported_outputs.items()]
        super().__init__(name, inputs=in_ports, outputs=out_ports, dt=dt, feedthrough=True)
        self._check_local_wiring()
        self.schedule = compile_schedule(self)
        self.feedthrough = self.schedule.input_reaches_output()

    # --- construction-time checks -------------------------------------------------------------
    def _member(self, blk: str) -> Block:
        try:
            return self.blocks[blk]
        except KeyError:
            raise WiringError(
                f"diagram {self.name!r} has no block {blk!r}; blocks: {sorted(self.blocks)}"
            ) from None

    def _exported_input_port(self, name: str, refs: list[str]) -> Port:
        if not refs:
            raise WiringError(f"diagram {self.name!r}: exported input {name!r} drives nothing")
        ports = []
        for ref in refs:
            blk, prt = split_ref(ref)
            ports.append(self._member(blk).input_port(prt))
        first = ports[0]
        for ref, p in zip(refs[1:], ports[1:], strict=True):
            _check_compatible(f"{self.name}.{name}", first, ref, p)
        return Port(name, first.shape, first.unit, first.dtype)

    def _exported_output_port(self, name: str, ref: str) -> Port:
        blk, prt = split_ref(ref)
        p = self._member(blk).output_port(prt)
        return Port(name, p.shape, p.unit, p.dtype)

    def _check_local_wiring(self) -> None:
        drivers: dict[str, str] = {}

        def claim(dst: str, src: str) -> None:
            if dst in drivers:
                raise WiringError(
                    f"diagram {self.name!r}: input {dst} has two drivers: {drivers[dst]} and {src}"
                )
            drivers[dst] = src

        for src, dst in self.connections:
            sblk, sprt = split_ref(src)
            dblk, dprt = split_ref(dst)
            sp = self._member(sblk).output_port(sprt)
            dp = self._member(dblk).input_port(dprt)
            _check_compatible(src, sp, dst, dp)
            claim(dst, src)
        for name, refs in self.exported_inputs.items():
            for ref in refs:
                claim(ref, f"diagram input {name!r}")
        for bname, blk in self.blocks.items():
            for pname in blk.inputs:
                if f"{bname}.{pname}" not in drivers:
                    raise WiringError(
                        f"diagram {self.name!r}: input {bname}.{pname} is not connected "
                        f"(connect it or export it as a diagram input)"
                    )
            ratio = blk.dt / self.dt
            if abs(ratio - round(ratio)) > 1e-9 * ratio or round(ratio) < 1:
                raise RateError(
                    f"diagram {self.name!r}: block {bname!r} has period {blk.dt:.6g} s, "
                    f"not an integer multiple of the base period {self.dt:.6g} s"
                )

    # --- block behaviour -----------------------------------------------------------------------
    def state_vars(self):
        """The diagram state's three entries; each leaf declares its own state (``schedule.leaves``)."""
        return (StateVar("tick", (), "int64", "k", "base ticks since step 0", batched=False),
                StateVar("leaves", (), "object", description="leaf states in schedule order", batched=False),
                StateVar("held", (), "object", description="outputs multirate leaves hold", batched=False))

    def initial_state(self, batch: int, rng=None, *, seed: int = 0, trials: Sequence[int] | None = None) -> State:
        """The diagram state at step 0; ``seed``/``trials`` select the per-trial random streams.

        A diagram state is ``{"tick": k, "leaves": [...], "held": [...]}``: the base tick, every
        leaf's own (declared) state in schedule order (``self.schedule.leaves``), and the outputs
        multirate leaves hold between their ticks.
        """
        return self.schedule.initial_state(batch, seed=seed, trials=trials)

    def output(self, state: State, u):
        """Exported outputs now; inputs that no exported output depends on may be left out of ``u``."""
        leaves, held = list(state["leaves"]), list(state["held"])
        outs = self.schedule.run(state["tick"], u, leaves, held, advance=False)
        for name, (i, _) in self.schedule.outputs.items():
            if outs[i] is None:
                missing = sorted(set(self.inputs) - set(u or {}))
                raise WiringError(f"diagram {self.name!r}: output {name!r} depends on inputs {missing} not given")
        return self.schedule.exported(outs)

    def update(self, state: State, u) -> State:
        return self.step(state, u)[1]

    def step(self, state: State, u):
        leaves, held = list(state["leaves"]), list(state["held"])
        outs = self.schedule.run(state["tick"], u, leaves, held)
        return self.schedule.exported(outs), {"tick": state["tick"] + 1, "leaves": leaves, "held": held}

    def to_control(self):
        """The whole diagram as one python-control system (every leaf must be linear)."""
        from magctl.core.linearize import diagram_to_control

        return diagram_to_control(self)

    def compile(self):
        """This diagram as one generated, numba-compiled step (:class:`magctl.core.compiled.CompiledDiagram`).

        Raises :class:`magctl.core.compiled.NotCompilable`, naming the block, when a leaf has no kernel.
        """
        from magctl.core.compiled import compile_diagram

        return compile_diagram(self)

    def linearize(self, state: State, u=None, eps: float = 1e-6):
        """Linearisation about ``state`` and inputs ``u`` as a ``control.StateSpace``."""
        from magctl.core.linearize import linearize_diagram

        return linearize_diagram(self, state, u, eps=eps)


def _check_compatible(src: str, sp: Port, dst: str, dp: Port) -> None:
    if sp.shape != dp.shape:
        raise WiringError(f"shape mismatch: {src} is {list(sp.shape)} but {dst} expects {list(dp.shape)}")
    if sp.unit != dp.unit:
        raise WiringError(f"unit mismatch: {src} is in {sp.unit!r} but {dst} expects {dp.unit!r}")
    if np.dtype(sp.dtype).kind != np.dtype(dp.dtype).kind:
        raise WiringError(f"type mismatch: {src} is {sp.dtype} but {dst} expects {dp.dtype}")


# ------------------------------------------------------------------------------------------------
# flattening (the schedule itself: magctl.core.schedule)


def _flatten(diagram: Diagram, prefix: str = ""):
    """Leaves, the driver of every leaf input, and the leaf source of every exported output.

    Returns ``(leaves, drivers, exported_in, exported_out)`` where ``drivers`` maps
    ``(leaf_path, port)`` to ``("leaf", path, port)`` or ``("ext", name)``.
    """
    leaves: list[tuple[str, Block]] = []
    drivers: dict[tuple[str, str], tuple] = {}
    child_in: dict[str, dict[str, list[tuple[str, str]]]] = {}
    child_out: dict[str, dict[str, tuple[str, str]]] = {}
    for bname, blk in diagram.blocks.items():
        path = f"{prefix}{bname}"
        if isinstance(blk, Diagram):
            sub_leaves, sub_drivers, sub_in, sub_out = _flatten(blk, prefix=f"{path}/")
            leaves += sub_leaves
            # inner drivers that come from the child's own exported inputs are resolved below
            for key, drv in sub_drivers.items():
                if drv[0] != "ext":
                    drivers[key] = drv
            child_in[bname] = sub_in
            child_out[bname] = sub_out
        else:
            leaves.append((path, blk))
            child_in[bname] = {p: [(path, p)] for p in blk.inputs}
            child_out[bname] = {p: (path, p) for p in blk.outputs}

    def leaf_sources(ref: str) -> tuple[str, str]:
        b, p = split_ref(ref)
        return child_out[b][p]

    def leaf_sinks(ref: str) -> list[tuple[str, str]]:
        b, p = split_ref(ref)
        return child_in[b][p]

    for src, dst in diagram.connections:
        lp, lport = leaf_sources(src)
        for sink in leaf_sinks(dst):
            drivers[sink] = ("leaf", lp, lport)
    exported_in: dict[str, list[tuple[str, str]]] = {}
    for name, refs in diagram.exported_inputs.items():
        sinks = [s for ref in refs for s in leaf_sinks(ref)]
        exported_in[name] = sinks
        for sink in sinks:
            drivers[sink] = ("ext", name)
    exported_out = {name: leaf_sources(ref) for name, ref in diagram.exported_outputs.items()}
    return leaves, drivers, exported_in, exported_out


def compile_schedule(diagram: Diagram) -> Schedule:
    leaves, drivers, _exported_in, exported_out = _flatten(diagram)
    return Schedule(diagram, leaves, drivers, exported_out)
