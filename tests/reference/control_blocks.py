"""Numpy references of the control layer's small blocks: the 30 Hz PI servo and the go-to/patrol guards."""

from __future__ import annotations

import numpy as np

from magctl.control.guards import ArrivalStatus, Patrol
from magctl.control.servo import Servo
from magctl.control.status import Status
from reference.core_blocks import NumpyForm, SteppedForm


class RefServo(SteppedForm, Servo):
    """``v = Kp e + Ki I`` on the position error, its norm capped (or held constant) as the robot's speed and
    its direction the heading; the integral held while saturated (or clamped to the cap), frozen on hold or
    an unusable estimate."""

    def step(self, state, u):
        e = u["target"] - u["robot_est"]
        ok = np.isfinite(e).all(axis=1)
        if "hold" in u:
            ok &= ~np.asarray(u["hold"], dtype=bool)
        e = np.where(ok[:, None], e, 0.0)
        dist = np.sqrt(np.einsum("bi,bi->b", e, e))
        arrived = ok & (dist < self.arrive_tol)
        cap = self.speed_max
        if "speed_cap" in u:
            cap = np.minimum(cap, np.maximum(u["speed_cap"], 0.0))
        raw = self.kp * e + self.ki * state["I"]
        mag = np.sqrt(np.einsum("bi,bi->b", raw, raw))
        sat = mag > cap
        speed = np.minimum(mag, cap)
        if self.constant_speed:
            speed = np.broadcast_to(cap, mag.shape).astype(float)
            sat = mag > 0
        moving = ok & ~arrived
        speed = np.where(moving, speed, 0.0)
        heading = np.where(mag > 0, np.arctan2(raw[:, 1], raw[:, 0]), state["heading"])
        sat = sat & moving
        out = {"speed": speed, "heading": heading, "arrived": arrived & ok, "saturated": sat}
        integrate = ok & ~arrived
        if self.anti_windup:
            integrate &= ~sat
        I = state["I"] + self.dt * e * integrate[:, None]
        if not self.anti_windup and self.ki > 0:
            mag = self.ki * np.sqrt(np.einsum("bi,bi->b", I, I))
            I = I * np.where(mag > cap, cap / np.where(mag > 0, mag, 1.0), 1.0)[:, None]
        return out, {"I": I, "heading": heading}



class RefArrivalStatus(NumpyForm, ArrivalStatus):
    def output(self, state, u):
        lost, arrived = u["lost"].astype(bool), u["arrived"].astype(bool)
        status = np.where(lost, Status.TRACKING_LOST, np.where(arrived, Status.CONVERGED, Status.RUNNING))
        return {"status": status.astype(np.int64)}


class RefPatrol(NumpyForm, Patrol):
    def output(self, state, u):
        running = np.full(state["i"].shape, Status.RUNNING, dtype=np.int64)
        return {"target": self.waypoints[state["i"]], "status": running, "lap": state["lap"].copy()}

    def update(self, state, u):
        d = u["robot_est"] - self.waypoints[state["i"]]
        arrived = np.hypot(d[:, 0], d[:, 1]) < self.tol
        i = np.where(arrived, (state["i"] + 1) % len(self.waypoints), state["i"])
        lap = state["lap"] + (arrived & (i == 0))
        return {"i": i, "lap": lap}


REFERENCES = {Servo: RefServo, ArrivalStatus: RefArrivalStatus, Patrol: RefPatrol}
