"""Closed-loop push trials: simulated time per wall-clock second, batch of 100 trials in lockstep on one core.

The full 30 Hz loop of :func:`magctl.loops.push_loop` (drive → coils → robot → spheres → camera in
positions mode → Kalman tracker → push task → servo) for a front push (K_c = 1, δ(0) from the model) and
a side push, from the start of a trial. Speed = (batch × simulated seconds) / wall seconds; target
≥ 5000× real time for a batch of 100 (issue 7). A second, instrumented run times every leaf block's
``output`` + ``update`` (or ``step``, which feedthrough blocks get once per frame) per step at B = 100
and B = 1, to show where the time goes, and a front push at B = 1000 shows how the lockstep batch
scales (informational, no target).
"""

from __future__ import annotations

import time

from magctl import FRAME_PERIOD_S
from magctl.core import simulate
from magctl.loops import Experiment, push_loop

BATCH = 100
SPEED_TARGET = 5000.0
EXPERIMENTS = {
    "front": Experiment("front", task=dict(kc=1.0, delta0=127e-6), label="K_c=1, model"),
    "side": Experiment("side", label="side push, default task"),
}


def _speed(exp: Experiment, frames: int, batch: int, repeats: int) -> tuple[float, float]:
    """Best-of-``repeats`` wall time of ``frames`` steps, and the resulting speed (× real time)."""
    diagram = push_loop(exp)
    simulate(diagram, 2, batch=batch, seed=0)   # flow map solve and caches, not timed
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        simulate(diagram, frames, batch=batch, seed=0, record=["controller/task.status"])
        best = min(best, time.perf_counter() - t0)
    return best, batch * frames * FRAME_PERIOD_S / best


def _per_block(exp: Experiment, frames: int, batch: int) -> dict[str, float]:
    """Mean cost [µs] of each leaf block's ``output`` + ``update`` / ``step`` per step (instrumented run)."""
    diagram = push_loop(exp)
    simulate(diagram, 2, batch=batch, seed=0)
    cost: dict[str, float] = {}
    busy: set[str] = set()      # step() may call the block's own output/update: time the outer call only
    for leaf in diagram.schedule.leaves:
        block, path = leaf.block, leaf.path
        cost[path] = 0.0
        for meth in ("output", "update", "step"):
            inner = getattr(block, meth)

            def timed(state, u, _inner=inner, _path=path):
                if _path in busy:
                    return _inner(state, u)
                busy.add(_path)
                t0 = time.perf_counter()
                try:
                    return _inner(state, u)
                finally:
                    cost[_path] += time.perf_counter() - t0
                    busy.discard(_path)

            setattr(block, meth, timed)
    t0 = time.perf_counter()
    simulate(diagram, frames, batch=batch, seed=0, record=["controller/task.status"])
    total = time.perf_counter() - t0
    for leaf in diagram.schedule.leaves:   # drop the instance overrides again
        for meth in ("output", "update", "step"):
            vars(leaf.block).pop(meth, None)
    table = {f"{path}_us": 1e6 * c / frames for path, c in sorted(cost.items(), key=lambda kv: -kv[1])}
    table["total_us"] = 1e6 * total / frames
    table["framework_us"] = table["total_us"] - sum(1e6 * c / frames for c in cost.values())
    return table


def run(quick: bool = False) -> dict:
    frames = 150 if quick else 600
    repeats = 1 if quick else 3
    out: dict = {"batch": BATCH, "frames": frames, "speed_target_x": SPEED_TARGET}
    for name, exp in EXPERIMENTS.items():
        wall, speed = _speed(exp, frames, BATCH, repeats)
        out[name] = {
            "controller": exp.label,
            "wall_s": wall,
            "step_ms": 1e3 * wall / frames,
            "speed_x": speed,
            "speed_met": speed >= SPEED_TARGET,
            "per_block_b100_us": _per_block(exp, frames // 2, BATCH),
            "per_block_b1_us": _per_block(exp, frames // 2, 1),
        }
    # the loop is bound by the number of numpy calls per step, not by the batch: larger batches run faster
    big = 250 if quick else 1000
    wall, speed = _speed(EXPERIMENTS["front"], frames // 2, big, 1)
    out["front_large_batch"] = {"batch": big, "step_ms": 2e3 * wall / frames, "speed_x": speed}
    out["speed_met"] = all(out[name]["speed_met"] for name in EXPERIMENTS)
    return out


if __name__ == "__main__":
    import json

    print(json.dumps(run(), indent=2, default=float))
