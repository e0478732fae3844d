"""STAND-IN controller blocks for rig tasks, until ``magctl.control`` provides the real ones.

* :class:`StandinServo` — proportional visual servo (the PI servo of ``magctl.control.servo`` replaces it);
* :class:`StandinDrive` — speed and heading to a field command, the inverse of the stand-in robot's
  speed law (``magctl.plant.drive`` replaces it);
* :class:`StandinFrontPush` — the front-pushing procedure of paper §V-A with the learning law
  eq 13 (``magctl.control.push`` replaces it).

:class:`TrackingGuard` is not a stand-in: it is the rig's rule that a task stops
the robot while tracking is lost instead of driving blind.
"""

from __future__ import annotations

import numpy as np

from magctl import FRAME_PERIOD_S
from magctl.core.block import Block
from magctl.core.ports import Port

# task status codes on a task diagram's ``status`` output
RUNNING, DONE, FAILED, LOST = 0, 1, 2, 3
STATUS_NAMES = {RUNNING: "running", DONE: "done", FAILED: "failed", LOST: "lost"}


def _norm(v: np.ndarray) -> np.ndarray:
    return np.sqrt(np.einsum("bi,bi->b", v, v))


class StandinServo(Block):
    """Proportional servo: ``speed = min(kp·‖e‖, v_max)`` along ``heading = atan2(e)``, ``e = target − robot``.

    Within ``tol`` of the target the robot stops and ``arrived`` is set.
    """

    def __init__(self, name: str, kp: float, v_max: float, tol: float, dt: float = FRAME_PERIOD_S):
        self.kp, self.v_max, self.tol = float(kp), float(v_max), float(tol)
        super().__init__(
            name,
            inputs=[Port("target", (2,), "m"), Port("robot_est", (2,), "m")],
            outputs=[Port("speed", (), "m/s"), Port("heading", (), "rad"), Port("arrived", (), "1", "bool")],
            dt=dt, feedthrough=True,
        )

    def output(self, state, u):
        e = u["target"] - u["robot_est"]
        dist = _norm(e)
        arrived = dist < self.tol
        speed = np.where(arrived, 0.0, np.minimum(self.kp * dist, self.v_max))
        return {"speed": speed, "heading": np.arctan2(e[:, 1], e[:, 0]), "arrived": arrived}


class Tee(Block):
    """Pass-through ``y = u`` that lets one exported diagram input feed several blocks."""

    def __init__(self, name: str, shape=(), unit: str = "1", dtype: str = "float64", dt: float = FRAME_PERIOD_S):
        super().__init__(name, inputs=[Port("u", tuple(shape), unit, dtype)],
                         outputs=[Port("y", tuple(shape), unit, dtype)], dt=dt, feedthrough=True)

    def output(self, state, u):
        return {"y": u["u"]}


class TrackingGuard(Block):
    """Zero speed while tracking is lost: ``speed_out = 0 if lost else speed``; ``stopped`` flags it."""

    def __init__(self, name: str, dt: float = FRAME_PERIOD_S):
        super().__init__(
            name,
            inputs=[Port("speed", (), "m/s"), Port("lost", (), "1", "bool")],
            outputs=[Port("speed", (), "m/s"), Port("stopped", (), "1", "bool")],
            dt=dt, feedthrough=True,
        )

    def output(self, state, u):
        lost = u["lost"].astype(bool)
        return {"speed": np.where(lost, 0.0, u["speed"]), "stopped": lost}


class ArrivalStatus(Block):
    """Status of a go-to: ``DONE`` once arrived, ``LOST`` while tracking is lost, else ``RUNNING``."""

    def __init__(self, name: str, dt: float = FRAME_PERIOD_S):
        super().__init__(name, inputs=[Port("arrived", (), "1", "bool"), Port("lost", (), "1", "bool")],
                         outputs=[Port("status", (), "1")], dt=dt, feedthrough=True)

    def output(self, state, u):
        lost, arrived = u["lost"].astype(bool), u["arrived"].astype(bool)
        return {"status": np.where(lost, float(LOST), np.where(arrived, float(DONE), float(RUNNING)))}


class Patrol(Block):
    """Cycle through waypoints forever: the target moves on when the robot is within ``tol`` of it.

    Used for long runs (the soak benchmark); its ``status`` is always ``RUNNING``.
    """

    def __init__(self, name: str, waypoints, tol: float, dt: float = FRAME_PERIOD_S):
        self.waypoints = np.asarray(waypoints, dtype=float).reshape(-1, 2)
        self.tol = float(tol)
        super().__init__(name, inputs=[Port("robot_est", (2,), "m")],
                         outputs=[Port("target", (2,), "m"), Port("status", (), "1"), Port("lap", (), "1")],
                         dt=dt, feedthrough=False)

    def initial_state(self, batch, rng=None):
        return {"i": np.zeros(batch, dtype=int), "lap": np.zeros(batch)}

    def output(self, state, u):
        return {"target": self.waypoints[state["i"]], "status": np.full(state["i"].shape, float(RUNNING)),
                "lap": state["lap"].copy()}

    def update(self, state, u):
        arrived = _norm(u["robot_est"] - self.waypoints[state["i"]]) < self.tol
        i = np.where(arrived, (state["i"] + 1) % len(self.waypoints), state["i"])
        lap = state["lap"] + (arrived & (i == 0))
        return {"i": i, "lap": lap}


class StandinDrive(Block):
    """Speed and heading → field command at a fixed frequency.

    ``b_static = B0 (cos h, sin h)``, ``freq = f0``, ``b_osc = b_ref · v / (s · f0)`` (clipped
    to ``b_osc_max``) — the inverse of :class:`magctl.rig.standin.StandinRobot`'s speed law.
    """

    def __init__(self, name: str, b0: float, f0: float, step_max: float, b_ref: float, b_osc_max: float,
                 dt: float = FRAME_PERIOD_S):
        self.b0, self.f0, self.step_max, self.b_ref, self.b_osc_max = b0, f0, step_max, b_ref, b_osc_max
        super().__init__(
            name,
            inputs=[Port("speed", (), "m/s"), Port("heading", (), "rad")],
            outputs=[Port("b_static", (2,), "T"), Port("b_osc", (), "T"), Port("freq", (), "1/s")],
            dt=dt, feedthrough=True,
        )

    def output(self, state, u):
        h = u["heading"]
        v = np.maximum(u["speed"], 0.0)
        b_osc = np.minimum(self.b_ref * v / (self.step_max * self.f0), self.b_osc_max)
        return {"b_static": self.b0 * np.stack([np.cos(h), np.sin(h)], axis=1), "b_osc": b_osc,
                "freq": np.where(v > 0, self.f0, 0.0)}


class StandinFrontPush(Block):
    """Front-pushing task of paper §V-A for sphere 0, with the learning law of eq 13.

    Per attempt i: servo to ``P_ri`` behind the sphere on the line from ``P_s`` to ``P_g``;
    push along it towards ``P_o(i) = P_g + δ(i)`` (eq 10) until ``‖P_s − P_o‖ < ε_p``
    (eq 11); retreat along the line; stop when ``‖P_s − P_g‖ < ε_p`` (eq 12), otherwise
    ``δ(i+1) = δ(i) + K_c (P_g − P_s)`` (eq 13) and repeat, up to ``max_attempts``.
    While tracking is lost the task holds its phase and reports ``LOST``.

    Ports: inputs ``robot_est`` (2,) m, ``spheres_est`` (N, 2) m, ``lost``; outputs
    ``target`` (2,) m, ``status`` (code, see :data:`STATUS_NAMES`), ``attempt`` (i, from 0).
    """

    INIT, APPROACH, PUSH, RETREAT, FINISHED = -1, 0, 1, 2, 3

    def __init__(self, name: str, n_spheres: int, goal, *, kc: float, delta0, eps_p: float, contact: float,
                 gap: float, retreat: float, tol: float, max_attempts: int, dt: float = FRAME_PERIOD_S):
        self.goal = np.asarray(goal, dtype=float).reshape(2)
        self.kc, self.eps_p, self.contact, self.gap = float(kc), float(eps_p), float(contact), float(gap)
        self.delta0 = np.broadcast_to(np.asarray(delta0, dtype=float), (2,)).copy()
        self.retreat, self.tol, self.max_attempts = float(retreat), float(tol), int(max_attempts)
        super().__init__(
            name,
            inputs=[Port("robot_est", (2,), "m"), Port("spheres_est", (n_spheres, 2), "m"),
                    Port("lost", (), "1", "bool")],
            outputs=[Port("target", (2,), "m"), Port("status", (), "1"), Port("attempt", (), "1")],
            dt=dt, feedthrough=True,
        )

    def initial_state(self, batch, rng=None):
        return {"phase": np.full(batch, self.INIT), "delta": np.tile(self.delta0, (batch, 1)),
                "attempt": np.zeros(batch), "aim": np.zeros((batch, 2)), "dir": np.tile([1.0, 0.0], (batch, 1)),
                "po": np.zeros((batch, 2)), "result": np.full(batch, float(RUNNING))}

    def output(self, state, u):
        ph = state["phase"]
        target = np.where((ph == self.INIT)[:, None], u["robot_est"], state["aim"])
        status = np.where(u["lost"].astype(bool) & (ph != self.FINISHED), float(LOST), state["result"])
        return {"target": target, "status": status, "attempt": state["attempt"].copy()}

    def _plan(self, ps, delta):
        """Direction of the pushing line, approach point P_ri and end point P_o (eq 10)."""
        g = self.goal[None, :] - ps
        n = _norm(g)
        d = np.where((n > 0)[:, None], g / np.where(n > 0, n, 1.0)[:, None], np.array([[1.0, 0.0]]))
        return d, ps - d * (self.contact + self.gap), self.goal[None, :] + delta

    def update(self, state, u):
        r, ps = u["robot_est"], u["spheres_est"][:, 0, :]
        ok = ~u["lost"].astype(bool)
        ph = state["phase"].copy()
        aim, d, po = state["aim"].copy(), state["dir"].copy(), state["po"].copy()
        delta, attempt, result = state["delta"].copy(), state["attempt"].copy(), state["result"].copy()
        at_aim = _norm(r - aim) < self.tol

        def start_attempt(mask):
            dd, pri, pp = self._plan(ps, delta)
            d[mask], aim[mask], po[mask] = dd[mask], pri[mask], pp[mask]
            ph[mask] = self.APPROACH

        start_attempt(ok & (state["phase"] == self.INIT))

        go_push = ok & (state["phase"] == self.APPROACH) & at_aim
        aim[go_push] = po[go_push] - d[go_push] * self.contact
        ph[go_push] = self.PUSH

        # eq 11: the sphere is within eps_p of P_o (or the robot has reached the end of the push line)
        pushed = (_norm(ps - po) < self.eps_p) | at_aim
        go_back = ok & (state["phase"] == self.PUSH) & pushed
        aim[go_back] = r[go_back] - d[go_back] * self.retreat
        ph[go_back] = self.RETREAT

        back = ok & (state["phase"] == self.RETREAT) & at_aim
        err = self.goal[None, :] - ps
        done = back & (_norm(err) < self.eps_p)  # eq 12
        again = back & ~done
        delta[again] += self.kc * err[again]  # eq 13
        attempt[again] += 1
        failed = again & (attempt >= self.max_attempts)
        start_attempt(again & ~failed)
        finished = done | failed
        ph[finished] = self.FINISHED
        aim[finished] = r[finished]
        result[done], result[failed] = float(DONE), float(FAILED)
        return {"phase": ph, "delta": delta, "attempt": attempt, "aim": aim, "dir": d, "po": po, "result": result}
