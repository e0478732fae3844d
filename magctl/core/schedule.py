"""The schedule: a diagram flattened into its leaf blocks in evaluation order, and the one step routine that runs it.

:func:`magctl.core.diagram.compile_schedule` builds a diagram's :class:`Schedule` (``diagram.schedule``): every leaf
block in feedthrough order, and for every leaf input the leaf output (or diagram input, :data:`EXTERNAL`) that drives
it. :meth:`Schedule.run` is the interpreted engine's tick, behind ``simulate``, ``Diagram.output``/``update``/``step``
and the rig; the compiled engine (:mod:`magctl.core.compiled`) and the linear export (:mod:`magctl.core.linearize`)
read the same schedule. They import this module, not :mod:`magctl.core.diagram`, whose methods call them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from magctl.core.block import Block, State
from magctl.core.errors import AlgebraicLoopError
from magctl.core.random import TrialStreams

EXTERNAL = -1
"""Leaf index standing for the diagram's own inputs in a schedule's wiring."""

_STEP, _OUTPUT_UPDATE, _OUTPUT = "step", "output+update", "output"


@dataclass
class Leaf:
    """A leaf block of a flattened diagram."""

    path: str
    block: Block
    ratio: int
    wiring: list[tuple[str, int, str]]  # (input port, source leaf index or EXTERNAL, source port)


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

    def __init__(self, diagram: Block, leaves, drivers, exported_out):
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
