"""Diagrams: blocks wired by port name; a diagram is itself a block.

Wiring is validated when the diagram is built, and every error names the
block and port at fault: unknown names, an input with no driver or with two,
shape or unit mismatches, sample periods that are not multiples of the base
period, and algebraic loops (listing the cycle).

For execution a diagram is flattened into its leaf blocks (nested diagrams
dissolve, so nesting never invents an algebraic loop) and compiled into a
:class:`Schedule`: leaves in feedthrough order, and for every leaf input the
leaf output (or diagram input) that drives it.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from magctl import FRAME_PERIOD_S
from magctl.core.block import Block, State, StateVar
from magctl.core.errors import AlgebraicLoopError, RateError, WiringError
from magctl.core.ports import Port
from magctl.core.random import TrialStreams

EXTERNAL = -1
"""Leaf index standing for the diagram's own inputs in a schedule's wiring."""

_STEP, _OUTPUT_UPDATE, _OUTPUT = "step", "output+update", "output"


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
# flattening and scheduling


@dataclass
class Leaf:
    """A leaf block of a flattened diagram."""

    path: str
    block: Block
    ratio: int
    wiring: list[tuple[str, int, str]]  # (input port, source leaf index or EXTERNAL, source port)


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


class Schedule:
    """A flattened diagram in evaluation order.

    Attributes
    ----------
    leaves : list of Leaf
        Leaf blocks in an order where every feedthrough block follows the
        producers of its inputs.
    outputs : dict
        Exported output name → (leaf index, port).
    inputs : dict of str to Port
        The diagram's exported inputs.
    """

    def __init__(self, diagram: Diagram, leaves, drivers, exported_out):
        self.diagram = diagram
        self.base_dt = diagram.dt
        self.inputs = dict(diagram.inputs)
        index = {path: i for i, (path, _) in enumerate(leaves)}
        order = _feedthrough_order(leaves, drivers, index)
        pos = {old: new for new, old in enumerate(order)}
        self.leaves: list[Leaf] = []
        for old in order:
            path, blk = leaves[old]
            wiring = []
            for p in blk.inputs:
                drv = drivers[(path, p)]
                if drv[0] == "ext":
                    wiring.append((p, EXTERNAL, drv[1]))
                else:
                    wiring.append((p, pos[index[drv[1]]], drv[2]))
            self.leaves.append(Leaf(path, blk, int(round(blk.dt / self.base_dt)), wiring))
        self.outputs = {name: (pos[index[lp]], p) for name, (lp, p) in exported_out.items()}
        self.multirate = any(leaf.ratio != 1 for leaf in self.leaves)
        # flat per-leaf tables for the step loop
        self._n = len(self.leaves)
        self._blocks = [lf.block for lf in self.leaves]
        self._ratios = [lf.ratio for lf in self.leaves]
        self._feed = [lf.block.feedthrough for lf in self.leaves]
        self._wirings = [lf.wiring for lf in self.leaves]
        # how a leaf is stepped: its own step() or its kernel's; output then update (Block.step's default,
        # inlined); output only (a Python block with no state to advance: Block.update returns the state)
        self._mode = [_STEP if (type(b).step is not Block.step or (b.feedthrough and b.kernel_driver())) else
                      (_OUTPUT if (type(b).update is Block.update and not b.kernel_driver()) else _OUTPUT_UPDATE)
                      for b in self._blocks]

    def signal_names(self) -> list[tuple[int, str, str]]:
        """Every leaf output as (leaf index, port, ``"path.port"``)."""
        return [(i, p, f"{lf.path}.{p}") for i, lf in enumerate(self.leaves) for p in lf.block.outputs]

    def consumers(self, leaf: int, port: str) -> list[str]:
        return [
            f"{lf.path}.{p}" for lf in self.leaves for p, j, q in lf.wiring if j == leaf and q == port
        ]

    def input_reaches_output(self) -> bool:
        """Whether some exported input reaches an exported output through feedthrough leaves."""
        reached = set()
        for i, lf in enumerate(self.leaves):
            if lf.block.feedthrough and any(j == EXTERNAL or j in reached for _, j, _ in lf.wiring):
                reached.add(i)
        return any(i in reached for i, _ in self.outputs.values())

    # --- execution: the one step routine behind simulate, Diagram.output/update/step and the rig ------
    def initial_state(self, batch: int, *, seed: int = 0, trials: Sequence[int] | None = None) -> State:
        trials = list(range(batch)) if trials is None else list(trials)
        if len(trials) != batch:
            raise ValueError(f"got {len(trials)} trial indices for a batch of {batch}")
        states = []
        for lf in self.leaves:
            rng = TrialStreams.for_block(seed, trials, lf.path) if lf.block.uses_random else None
            states.append(lf.block.initial_state(batch, rng))
        return {"tick": 0, "leaves": states, "held": [None] * len(self.leaves)}

    def run(self, tick: int, u, leaf_states: list, held: list, advance: bool = True) -> list[dict]:
        """One base tick: every leaf's outputs in feedthrough order, then (``advance``) every next state.

        A feedthrough leaf is stepped once (``block.step``: outputs and next state together, its
        inputs being known); a leaf without feedthrough gives its outputs from its state first and is
        updated once every output of the tick exists. Next states are held back until all outputs
        are evaluated, then written into ``leaf_states``; a leaf of period ``r`` base ticks runs
        on ticks ``k ≡ 0 (mod r)`` and holds its outputs (kept in ``held``) in between.

        ``leaf_states`` and ``held`` are the caller's own lists and are updated in place; the
        leaf states in them are never modified. Returns the outputs, indexed by leaf (the
        last entry holds the diagram inputs ``u``).
        """
        n = self._n
        blocks, ratios, feed, wirings, mode = self._blocks, self._ratios, self._feed, self._wirings, self._mode
        multirate = self.multirate
        outs: list = [None] * (n + 1)
        outs[EXTERNAL] = u or {}
        pending: list = [None] * n
        empty: dict = {}
        for i in range(n):
            r = ratios[i]
            if r != 1 and tick % r and held[i] is not None:
                outs[i] = held[i]
                continue
            if feed[i]:
                if advance:
                    ui = {p: outs[j][q] for p, j, q in wirings[i]}
                    m = mode[i]
                    if m is _STEP:
                        outs[i], pending[i] = blocks[i].step(leaf_states[i], ui)
                    else:
                        outs[i] = blocks[i].output(leaf_states[i], ui)
                        pending[i] = leaf_states[i] if m is _OUTPUT else blocks[i].update(leaf_states[i], ui)
                else:
                    try:
                        ui = {p: outs[j][q] for p, j, q in wirings[i]}
                    except (KeyError, TypeError):
                        continue  # an input not given (outputs only): this leaf's outputs stay None
                    outs[i] = blocks[i].output(leaf_states[i], ui)
            else:
                outs[i] = blocks[i].output(leaf_states[i], empty)
            if multirate:
                held[i] = outs[i]
        if advance:
            for i in range(n):
                r = ratios[i]
                if r != 1 and tick % r:
                    continue
                if feed[i]:
                    leaf_states[i] = pending[i]
                elif mode[i] is not _OUTPUT:
                    leaf_states[i] = blocks[i].update(leaf_states[i], {p: outs[j][q] for p, j, q in wirings[i]})
        return outs

    def gather(self, i: int, outs: list[dict], u) -> dict:
        """The inputs of leaf ``i`` given every leaf's outputs and the diagram inputs ``u``."""
        ext = u or {}
        return {p: (ext[q] if j == EXTERNAL else outs[j][q]) for p, j, q in self.leaves[i].wiring}

    def exported(self, outs: list[dict]) -> dict[str, np.ndarray]:
        return {name: outs[i][p] for name, (i, p) in self.outputs.items()}


def _feedthrough_order(leaves, drivers, index) -> list[int]:
    """Topological order on edges into feedthrough leaves; a cycle is an algebraic loop."""
    n = len(leaves)
    succ: list[set[int]] = [set() for _ in range(n)]
    indeg = [0] * n
    for (path, _port), drv in drivers.items():
        if drv[0] != "leaf":
            continue
        dst = index[path]
        if not leaves[dst][1].feedthrough:
            continue
        src = index[drv[1]]
        if dst not in succ[src]:
            succ[src].add(dst)
            indeg[dst] += 1
    ready = [i for i in range(n) if indeg[i] == 0]
    order: list[int] = []
    while ready:
        i = ready.pop(0)
        order.append(i)
        for j in sorted(succ[i]):
            indeg[j] -= 1
            if indeg[j] == 0:
                ready.append(j)
    if len(order) < n:
        raise AlgebraicLoopError([leaves[i][0] for i in _find_cycle(succ, set(range(n)) - set(order))])
    return order


def _find_cycle(succ: list[set[int]], nodes: set[int]) -> list[int]:
    """A cycle among ``nodes``; each of them has a predecessor among them, so walk backwards."""
    pred = {i: sorted(j for j in nodes if i in succ[j]) for i in nodes}
    node = min(nodes)
    walk, seen = [node], {node: 0}
    while True:
        node = pred[node][0]
        if node in seen:
            cycle = walk[seen[node]:]
            return cycle[::-1]
        seen[node] = len(walk)
        walk.append(node)


def compile_schedule(diagram: Diagram) -> Schedule:
    leaves, drivers, _exported_in, exported_out = _flatten(diagram)
    return Schedule(diagram, leaves, drivers, exported_out)
