"""Linear analysis of the 30 Hz visual-servo loop (paper §II, §VI-A).

Along the line from the robot to its target the unsaturated servo is a
single-axis loop of three magctl blocks:

* PI servo ``C(z) = Kp + Ki·T/(z − 1)`` acting on the position error,
* the robot as an integrator of the commanded speed ``P(z) = T/(z − 1)``
  (the drive turns speed into a field; within one frame the robot moves at
  the commanded speed, a forward-Euler step),
* the camera's processing latency ``z⁻ᵈ`` in the feedback path.

The closed loop from target ``r`` to position ``x`` is
``T(z) = C P / (1 + C P z⁻ᵈ)``. The loop is built from :mod:`magctl.core`
blocks and exported with :meth:`Diagram.to_control`, so python-control
(not a hand-rolled root finder) gives its poles, margins and step response.
Saturation of the speed at ``speed_max`` is outside this model; for steps
larger than ``speed_max / Kp`` the simulated response departs from it.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import control
import numpy as np

from magctl import FRAME_PERIOD_S
from magctl.core.diagram import Diagram
from magctl.core.errors import MagctlError
from magctl.core.linear import PI, Constant, Delay, Gain, Integrator, Sum
from magctl.plant.standin import KinematicRobot


class ServoAnalysisError(MagctlError):
    """Servo-loop parameters out of range (negative gains, negative delay)."""


@dataclass
class ServoLoopReport:
    """Numbers that describe the linear servo loop.

    Attributes
    ----------
    poles : ndarray of complex
        Closed-loop poles in the z-plane.
    stable : bool
        All poles strictly inside the unit circle.
    gain_margin, phase_margin_deg : float
        Classical margins of the loop transfer ``C P z⁻ᵈ`` (inf when not crossed).
    gain_crossover_rad_s, phase_crossover_rad_s : float
        Frequencies (rad/s) at which the margins are read.
    overshoot_ratio : float
        Peak overshoot of the unit step response as a fraction of the step.
    settling_time_s : float
        2 % settling time of the step response.
    """

    kp: float
    ki: float
    delay_frames: int
    poles: np.ndarray
    stable: bool
    gain_margin: float
    phase_margin_deg: float
    gain_crossover_rad_s: float
    phase_crossover_rad_s: float
    overshoot_ratio: float
    settling_time_s: float

    def to_dict(self, step_um: float | None = None) -> dict:
        d = {
            "kp_per_s": self.kp, "ki_per_s2": self.ki, "delay_frames": self.delay_frames,
            "poles": [{"re": float(p.real), "im": float(p.imag), "abs": float(abs(p))} for p in self.poles],
            "stable": self.stable, "gain_margin": self.gain_margin, "phase_margin_deg": self.phase_margin_deg,
            "gain_crossover_rad_s": self.gain_crossover_rad_s, "phase_crossover_rad_s": self.phase_crossover_rad_s,
            "overshoot_percent": 100.0 * self.overshoot_ratio, "settling_time_s": self.settling_time_s,
        }
        if step_um is not None:
            d["step_um"] = step_um
            d["overshoot_um"] = self.overshoot_ratio * step_um
        return d


def _check(kp: float, ki: float, delay_frames: int) -> None:
    if not np.isfinite(kp) or kp <= 0:
        raise ServoAnalysisError(f"kp={kp!r} 1/s must be positive")
    if not np.isfinite(ki) or ki < 0:
        raise ServoAnalysisError(f"ki={ki!r} 1/s² must be zero or positive")
    if int(delay_frames) != delay_frames or delay_frames < 0:
        raise ServoAnalysisError(f"delay_frames={delay_frames!r} must be a non-negative integer")


def _controller(kp: float, ki: float, dt: float):
    """The PI law; a pure gain when ``ki = 0`` so no uncontrollable integrator state is exported."""
    if ki > 0:
        return PI("pi", kp, ki, in_unit="m", out_unit="m/s", dt=dt)
    return Gain("pi", kp, in_unit="m", out_unit="m/s", dt=dt)


def servo_loop_diagram(kp: float, ki: float, delay_frames: int, dt: float = FRAME_PERIOD_S) -> Diagram:
    """The single-axis servo loop as a magctl diagram: input ``r`` (m), output ``x`` (m).

    Blocks: ``err = r − y_meas`` (Sum), ``pi`` (PI, unsaturated), ``robot`` (Integrator,
    speed → position) and ``camera`` (Delay of ``delay_frames``, omitted when 0).
    """
    _check(kp, ki, delay_frames)
    blocks = [Sum("err", "+-", unit="m", dt=dt), _controller(kp, ki, dt),
              Integrator("robot", in_unit="m/s", out_unit="m", dt=dt)]
    conns = [("err.y", "pi.e"), ("pi.u", "robot.u")] if ki > 0 else [("err.y", "pi.u"), ("pi.y", "robot.u")]
    if delay_frames > 0:
        blocks.append(Delay("camera", int(delay_frames), unit="m", dt=dt))
        conns += [("robot.y", "camera.u"), ("camera.y", "err.u1")]
    else:
        conns.append(("robot.y", "err.u1"))
    return Diagram("servo_loop", blocks, conns, inputs={"r": "err.u0"}, outputs={"x": "robot.y"}, dt=dt)


def closed_loop(kp: float, ki: float, delay_frames: int, dt: float = FRAME_PERIOD_S) -> control.StateSpace:
    """Closed-loop ``r → x`` state space exported from :func:`servo_loop_diagram`."""
    return servo_loop_diagram(kp, ki, delay_frames, dt).to_control()


def loop_transfer(kp: float, ki: float, delay_frames: int, dt: float = FRAME_PERIOD_S) -> control.StateSpace:
    """Open loop ``C P z⁻ᵈ`` from the magctl blocks (the loop broken at the error)."""
    _check(kp, ki, delay_frames)
    robot = Integrator("robot", in_unit="m/s", out_unit="m", dt=dt).to_control()
    open_ = control.series(_controller(kp, ki, dt).to_control(), robot)
    if delay_frames > 0:
        open_ = control.series(open_, Delay("camera", int(delay_frames), unit="m", dt=dt).to_control())
    return open_


def _step_metrics(sys: control.StateSpace, dt: float) -> tuple[float, float]:
    poles = np.abs(sys.poles()) if sys.nstates else np.array([0.0])
    slowest = float(np.max(poles)) if poles.size else 0.0
    # long enough for the slowest stable pole to decay below 1e-4
    n = 400 if slowest < 1e-9 else int(min(20000, max(400, np.log(1e-4) / np.log(min(slowest, 0.9999)) + 50)))
    t = np.arange(n) * dt
    resp = control.step_response(sys, T=t)
    y = np.squeeze(resp.outputs)
    final = 1.0
    overshoot = max(0.0, float(y.max()) - final)
    outside = np.flatnonzero(np.abs(y - final) > 0.02)
    settling = float(t[outside[-1] + 1]) if outside.size and outside[-1] + 1 < n else (0.0 if not outside.size
                                                                                      else float("inf"))
    return overshoot, settling


def analyse(kp: float, ki: float, delay_frames: int, dt: float = FRAME_PERIOD_S) -> ServoLoopReport:
    """Poles, margins and step metrics of the linear servo loop (python-control).

    Parameters
    ----------
    kp : float
        Proportional gain, (m/s) per m of error = 1/s.
    ki : float
        Integral gain, 1/s².
    delay_frames : int
        Camera processing latency in frames.
    """
    cl = closed_loop(kp, ki, delay_frames, dt)
    poles = np.asarray(cl.poles(), dtype=complex)
    stable = bool(np.all(np.abs(poles) < 1.0 - 1e-12))
    with warnings.catch_warnings():  # python-control evaluates the response at the integrator poles
        warnings.simplefilter("ignore", RuntimeWarning)
        gm, pm, wpc, wgc = control.margin(loop_transfer(kp, ki, delay_frames, dt))
    overshoot, settling = _step_metrics(cl, dt) if stable else (float("inf"), float("inf"))
    return ServoLoopReport(
        kp=float(kp), ki=float(ki), delay_frames=int(delay_frames), poles=poles, stable=stable,
        gain_margin=float(gm), phase_margin_deg=float(pm), gain_crossover_rad_s=float(wgc),
        phase_crossover_rad_s=float(wpc), overshoot_ratio=overshoot, settling_time_s=settling,
    )


def linear_step(kp: float, ki: float, delay_frames: int, step: float, steps: int,
                dt: float = FRAME_PERIOD_S) -> tuple[np.ndarray, np.ndarray]:
    """Linear-model response ``(t, x)`` to a target step of ``step`` metres."""
    t = np.arange(int(steps)) * dt
    resp = control.step_response(closed_loop(kp, ki, delay_frames, dt), T=t)
    return t, step * np.squeeze(resp.outputs)


# --- closed-loop simulation with the servo, camera and tracker blocks --------------------------------
# The plant of these simulations is the stand-in's kinematic robot (magctl.plant.standin.KinematicRobot):
# x[k+1] = x[k] + T·speed·(cos h, sin h), the integrator P(z) = T/(z − 1) of the linear analysis above.
def servo_step_diagram(servo, *, delay_frames: int, start=(1.0e-3, 1.0e-3), tracker_mode: str = "raw",
                       predict: bool = False, position_noise_px: float = 0.0, heading_noise: float = 0.0,
                       drop_probability: float = 0.0, spheres=(), pixel_size: float | None = None,
                       dt: float = FRAME_PERIOD_S):
    """Servo + camera (positions mode) + tracker + kinematic robot; exported input ``target`` (2,) m.

    Parameters
    ----------
    servo : magctl.control.servo.Servo
        The servo under test (its ``hold`` input, if any, is wired to the tracker's ``lost``).
    delay_frames : int
        Camera latency.
    tracker_mode : {"raw", "kalman"}
        ``predict=True`` makes the Kalman tracker extrapolate across the latency.

    Notes
    -----
    The camera starts primed (the robot has been at rest at ``start``), as the linear
    model's delay line starts at the initial position.
    """
    from magctl.sensing.camera import Camera
    from magctl.sensing.tracker import Tracker

    sph = np.asarray(spheres, dtype=float).reshape(-1, 2)
    n = sph.shape[0]
    robot = KinematicRobot("robot", start=start, dt=dt)
    still = Constant("spheres", sph, shape=sph.shape, unit="m", dt=dt)  # the servo loop leaves them where they are
    cam = Camera("camera", n_spheres=n, latency_frames=delay_frames, position_noise_px=position_noise_px,
                 heading_noise=heading_noise, drop_probability=drop_probability, pixel_size=pixel_size,
                 primed=(start, 0.0, sph), dt=dt)
    trk = Tracker("tracker", n_spheres=n, mode=tracker_mode, predict_frames=delay_frames if predict else 0,
                  pixel_size=pixel_size, position_noise_px=position_noise_px, dt=dt)
    conns = [("robot.position", "camera.position"), ("robot.heading", "camera.heading"),
             ("spheres.y", "camera.spheres"), ("camera.robot_meas", "tracker.robot_meas"),
             ("camera.heading_meas", "tracker.heading_meas"), ("camera.spheres_meas", "tracker.spheres_meas"),
             ("camera.valid", "tracker.valid"), ("tracker.robot_est", f"{servo.name}.robot_est"),
             (f"{servo.name}.speed", "robot.speed"), (f"{servo.name}.heading", "robot.heading")]
    if "hold" in servo.inputs:
        conns.append(("tracker.lost", f"{servo.name}.hold"))
    inputs = {"target": f"{servo.name}.target"}
    if "speed_cap" in servo.inputs:
        inputs["speed_cap"] = f"{servo.name}.speed_cap"
    return Diagram("servo_step", [robot, still, cam, trk, servo], conns, inputs=inputs,
                   outputs={"position": "robot.position", "arrived": f"{servo.name}.arrived"}, dt=dt)


def simulated_overshoot(position: np.ndarray, start: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Peak travel beyond the target along the start → target line, per trial (m); ``position`` is (B, T, 2)."""
    start, target = np.asarray(start, dtype=float), np.asarray(target, dtype=float)
    line = target - start
    length = np.linalg.norm(line)
    along = (position - start) @ (line / length)
    return np.maximum(along.max(axis=1) - length, 0.0)


def step_report(servo, *, delay_frames: int, step: float, steps: int = 450, start=(1.0e-3, 1.0e-3),
                pixel_size: float | None = None) -> dict:
    """Linear prediction and simulated step of ``step`` m along x: overshoots (µm) and trajectories.

    The simulation runs the servo block, the camera (positions mode, no noise) and the raw
    tracker around the kinematic robot, so saturation, the integral clamp and pixel
    quantisation are included; the linear model has none of them.
    """
    from magctl.core.simulation import simulate

    start = np.asarray(start, dtype=float)
    target = start + np.array([step, 0.0])
    res = simulate(servo_step_diagram(servo, delay_frames=delay_frames, start=start, pixel_size=pixel_size),
                   steps, inputs={"target": target})
    x = res["position"][0]
    t_lin, x_lin = linear_step(servo.kp, servo.ki, delay_frames, step, steps)
    arrived = np.flatnonzero(res["arrived"][0])
    return {
        "t_s": res.t, "sim_um": (x[:, 0] - start[0]) * 1e6, "linear_um": x_lin * 1e6,
        "sim_overshoot_um": float(simulated_overshoot(res["position"], start, target)[0] * 1e6),
        "linear_overshoot_um": float(max(0.0, x_lin.max() - step) * 1e6),
        "first_arrival_s": float(res.t[arrived[0]]) if arrived.size else None,
        "final_error_um": float(np.linalg.norm(x[-1] - target) * 1e6),
    }
