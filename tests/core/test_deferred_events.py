"""Python events taken off the tick (docs/core.md "Events off the tick"): a stepper that defers hands the flagged
trials over and keeps their flag up; a result merged before the next tick is the synchronous handling, one merged
later keeps what the ticks in between did to the elements the handler left alone."""

from __future__ import annotations

import numba
import numpy as np
import pytest

from magctl.core.block import Block, StateVar
from magctl.core.diagram import Diagram
from magctl.core.errors import MagctlError
from magctl.core.kernel import Kernel
from magctl.core.ports import Port


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def counter_step(b, params, state, next_state, inputs, outputs, base, noise):
    every, = params
    k, level, due = state
    nk, nlevel, ndue = next_state
    u, = inputs
    y, = outputs
    frame = k[b, 0] + 1
    y[b, 0] = level[b, 0]
    nk[b, 0] = frame
    if not due[b, 0]:                      # a pending event freezes the level; the count goes on
        nlevel[b, 0] = level[b, 0] + u[b, 0]
        ndue[b, 0] = frame % every == 0
    else:
        nlevel[b, 0] = level[b, 0]
        ndue[b, 0] = True


class Counter(Block):
    """Adds its input each frame; every ``every`` frames Python halves the level (the event)."""

    def __init__(self, every: int = 3, name: str = "counter", broken: bool = False):
        self.every, self.broken = int(every), broken
        super().__init__(name, inputs=[Port("u", (), "1")], outputs=[Port("y", (), "1")], feedthrough=True)

    def state_vars(self):
        return (StateVar("k", (), "int64"), StateVar("level", ()), StateVar("due", (), "bool"))

    def initial_state(self, batch, rng=None):
        return {"k": np.zeros(batch, np.int64), "level": np.zeros(batch), "due": np.zeros(batch, bool)}

    def kernel(self):
        return Kernel(step=counter_step, params=(self.every,), event="due")

    def handle_event(self, state, u):
        return {**state, "level": state["level"] / 2 + u["u"], "due": np.full(len(state["k"]), self.broken)}


def _diagram(block):
    return Diagram("d", [block], inputs={"u": f"{block.name}.u"}, outputs={"y": f"{block.name}.y"})


def _run(block, compiled: bool, us: np.ndarray, merge_after: int | None):
    """Outputs of ``len(us)`` ticks; ``merge_after``: None handles events in the tick, else each deferred one is
    merged before the tick ``merge_after`` ticks after the one that raised it."""
    d = _diagram(block)
    batch = us.shape[1]
    if compiled:
        stepper = d.compile().stepper(d.initial_state(batch), batch)
        target = stepper
    else:
        state = [d.initial_state(batch)]
        driver = block.kernel_driver()
        driver.forget_events()
        target = driver
    pending = []
    if merge_after is not None:
        target.defer = lambda req: pending.append((tick, req))
    ys = []
    for tick in range(len(us)):
        for raised, req in [p for p in pending if tick - p[0] >= merge_after]:
            pending.remove((raised, req))
            if compiled:
                stepper.apply_event(req, req.run())
            else:
                leaves = list(state[0]["leaves"])
                leaves[0] = driver.apply_event(leaves[0], req, req.run())
                state[0] = {**state[0], "leaves": leaves}
        if compiled:
            ys.append(stepper.step({"u": us[tick]})["y"].copy())
        else:
            out, state[0] = d.step(state[0], {"u": us[tick]})
            ys.append(np.asarray(out["y"]).copy())
    target.defer = None
    return np.array(ys)


@pytest.mark.parametrize("compiled", [True, False])
def test_a_deferred_event_merged_before_the_next_tick_is_the_synchronous_one(compiled):
    us = np.random.default_rng(3).normal(size=(20, 2))
    np.testing.assert_array_equal(_run(Counter(), compiled, us, 1), _run(Counter(), compiled, us, None))


@pytest.mark.parametrize("compiled", [True, False])
def test_a_late_merge_keeps_what_the_ticks_in_between_did(compiled):
    """Merged 2 ticks late: the level stays frozen one tick more (the kernel holds while its flag is up), the
    handler's level is merged, and the frame count the held tick advanced is kept (the handler left it alone)."""
    us = np.ones((9, 1))
    late = _run(Counter(every=3), compiled, us, 2)[:, 0]
    sync = _run(Counter(every=3), compiled, us, None)[:, 0]
    # sync: 0 1 2 | 3 → 3/2+1 = 2.5 at tick 3 ...; late: the level of tick 2's event is held through tick 3
    assert list(sync[:4]) == [0, 1, 2, 2.5] and list(late[:5]) == [0, 1, 2, 3, 2.5]


def test_a_merged_result_must_clear_the_flag():
    d = _diagram(Counter(broken=True))
    stepper = d.compile().stepper(d.initial_state(1), 1)
    got = []
    stepper.defer = got.append
    for _ in range(3):
        stepper.step({"u": np.ones(1)})
    (req,) = got
    with pytest.raises(MagctlError, match="left its event flag set"):
        stepper.apply_event(req, req.run())
