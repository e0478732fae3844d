"""Python events inside kernelled blocks: a kernel raises a per-trial flag, the block's Python handler runs at
the end of that tick for those trials only, in both engines and in the compiled stepper."""

from __future__ import annotations

import math

import numba
import numpy as np
import pytest

from magctl.core.block import Block, StateVar
from magctl.core.diagram import Diagram
from magctl.core.errors import MagctlError
from magctl.core.kernel import Kernel
from magctl.core.ports import Port
from magctl.core.simulation import simulate


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def replan_output(b, params, state, outputs):
    k, target, due, plans = state
    y, = outputs
    y[b, 0] = target[b, 0]


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def replan_update(b, params, state, next_state, inputs, base, noise):
    every, = params
    k, target, due, plans = state
    nk, ntarget, ndue, nplans = next_state
    u, = inputs
    frame = k[b, 0] + 1                  # read before the next state (the same arrays, in place) is written
    nk[b, 0] = frame
    ntarget[b, 0] = target[b, 0] + 0.5 * (u[b, 0] - target[b, 0])      # creep towards the input every frame
    ndue[b, 0] = (frame + b) % every == 0                                # trial b's events shifted by b
    nplans[b, 0] = plans[b, 0]


def plan(target: float, u: float, plans: int) -> float:
    """What only Python does here (a stand-in for an IPOPT solve): a new target from the last one."""
    return math.fsum([target, u, plans]) / 3.0 + math.sqrt(plans + 1.0)


class Replanner(Block):
    """Follows its input each frame; every ``every`` frames (offset by the batch row) Python replans."""

    def __init__(self, every: int, name: str = "replan", broken: bool = False):
        self.every, self.broken = int(every), broken
        super().__init__(name, inputs=[Port("u", (), "m")], outputs=[Port("y", (), "m")], feedthrough=False)

    def state_vars(self):
        return (StateVar("k", (), "int64"), StateVar("target", ()), StateVar("due", (), "bool"),
                StateVar("plans", (), "int64"))

    def initial_state(self, batch, rng=None):
        return {"k": np.zeros(batch, np.int64), "target": np.zeros(batch), "due": np.zeros(batch, bool),
                "plans": np.zeros(batch, np.int64)}

    def kernel(self):
        return Kernel(output=replan_output, update=replan_update, params=(self.every,), event="due")

    def handle_event(self, state, u):
        target = np.array([plan(t, x, p) for t, x, p in zip(state["target"], u["u"], state["plans"], strict=True)])
        return {**state, "target": target, "due": np.full(target.shape, self.broken), "plans": state["plans"] + 1}


def expected(us: np.ndarray, every: int, row: int) -> tuple[np.ndarray, int]:
    """The block written as a plain Python loop for one trial (batch row ``row``)."""
    target, plans, ys = 0.0, 0, []
    for k, u in enumerate(us):
        ys.append(target)
        target = target + 0.5 * (u - target)
        if (k + 1 + row) % every == 0:
            target, plans = plan(target, u, plans), plans + 1
    return np.array(ys), plans


def _diagram(block):
    return Diagram("d", [block], inputs={"u": f"{block.name}.u"}, outputs={"y": f"{block.name}.y"})


@pytest.mark.parametrize("engine", ["interpreted", "compiled"])
def test_events_run_python_for_the_flagged_trials_at_the_end_of_their_tick(engine):
    steps, batch, every = 40, 3, 7
    us = np.random.default_rng(0).normal(size=(batch, steps))
    r = simulate(_diagram(Replanner(every)), steps, batch=batch, inputs={"u": us}, engine=engine)
    for b in range(batch):
        ys, plans = expected(us[b], every, b)
        np.testing.assert_allclose(r["y"][b], ys, rtol=1e-15, atol=0)
        assert r.final_state["leaves"][0]["plans"][b] == plans
    assert len(set(r.final_state["leaves"][0]["plans"].tolist())) > 1 or steps % every == 0


def test_a_compiled_run_with_events_splits_and_resumes_like_one_run():
    steps, batch, every = 30, 2, 4
    us = np.random.default_rng(1).normal(size=(batch, steps))
    d = _diagram(Replanner(every))
    whole = simulate(d, steps, batch=batch, inputs={"u": us}, engine="compiled")
    first = simulate(d, 13, batch=batch, inputs={"u": us[:, :13]}, engine="compiled")
    rest = simulate(d, steps - 13, batch=batch, inputs={"u": us[:, 13:]}, state=first.final_state,
                    engine="interpreted")
    np.testing.assert_array_equal(np.concatenate([first["y"], rest["y"]], axis=1), whole["y"])


def test_the_compiled_stepper_handles_events_every_tick():
    steps, batch, every = 25, 3, 5
    us = np.random.default_rng(2).normal(size=(batch, steps))
    d = _diagram(Replanner(every))
    stepper = d.compile().stepper(d.initial_state(batch), batch)
    got = np.array([stepper.step({"u": us[:, k]})["y"].copy() for k in range(steps)]).T
    for b in range(batch):
        np.testing.assert_allclose(got[b], expected(us[b], every, b)[0], rtol=1e-15, atol=0)


@pytest.mark.parametrize("engine", ["interpreted", "compiled"])
def test_a_handler_that_leaves_its_flag_set_is_named(engine):
    d = _diagram(Replanner(3, broken=True))
    with pytest.raises(MagctlError, match="'replan': handle_event left its event flag set"):
        simulate(d, 10, batch=2, inputs={"u": np.ones((2, 10))}, engine=engine)
