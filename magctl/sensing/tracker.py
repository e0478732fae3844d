"""Tracker block: camera outputs → estimates of the robot pose and the spheres (paper §II).

Three modes:

``"raw"``
    The camera's measurement as the estimate (what the paper's servo saw);
    velocity by finite difference of the last two measurements.
``"kalman"`` (positions mode of the camera)
    A constant-velocity Kalman filter per object and axis (state ``[p, v]``,
    ``F = [[1, T], [0, 1]]``, ``H = [1, 0]``, white-noise acceleration ``Q`` from
    :func:`filterpy.common.Q_discrete_white_noise`, ``R = (σ_px·s)² + s²/12`` with
    the quantisation variance ``s²/12``). With ``predict_frames = d`` it
    reports ``p + d·T·v``, extrapolating across the camera latency.
``"particle"`` (images mode of the camera)
    A particle filter on the image gradient per object
    (:mod:`magctl.sensing.particle_filter`), resampled with filterpy.

Raw and Kalman modes are implemented once, by the per-trial kernel
:func:`magctl.sensing.kernels.tracker_step` (both engines run it); it is tested
against a batched numpy form (``tests/reference/sensing_blocks.py``) and against
filterpy's per-trial ``KalmanFilter``. Particle mode has no kernel and runs in Python.

Tracking loss: after ``max_coast`` frames without a valid detection (or
before the first one) ``lost`` is true and the estimates are not invented:
with ``on_loss="nan"`` they are NaN, with ``on_loss="hold"`` (default, so
closed-loop simulations stay finite) the last estimate is held with zero
velocity; consumers gate on ``lost`` (the servo's ``hold`` input).
"""

from __future__ import annotations

import copy

import numpy as np
from filterpy.common import Q_discrete_white_noise

from magctl import FRAME_PERIOD_S
from magctl.config import Params
from magctl.core.block import Block, StateVar
from magctl.core.errors import ParameterError
from magctl.core.kernel import Kernel
from magctl.core.ports import DIMENSIONLESS, Port
from magctl.sensing.camera import camera_params

MODES = ("raw", "kalman", "particle")
START_VELOCITY_VAR = (4e-4) ** 2
"""Velocity variance of a track's first estimate, m²/s²: up to the robot's top speed, 400 µm/s (paper §IV-C)."""


def cv_model(dt: float, accel_noise: float):
    """``F`` and ``Q`` of the constant-velocity model for one axis (filterpy's discrete white noise)."""
    F = np.array([[1.0, dt], [0.0, 1.0]])
    Q = Q_discrete_white_noise(dim=2, dt=dt, var=accel_noise**2 / dt)
    return F, Q


class Tracker(Block):
    """Tracker block.

    Parameters
    ----------
    name : str
    n_spheres : int
    mode : {"raw", "kalman", "particle"}
    predict_frames : int
        Frames to extrapolate the estimate forward (Kalman mode), normally the camera latency.
    on_loss : {"hold", "nan"}
        What the estimate ports carry while ``lost``.
    pixel_size, position_noise_px : float, optional
        Camera pixel (m) and noise (pixels) for ``R``; default from ``models/camera.toml``.
    params : Params, optional
        Parsed ``models/camera.toml``.
    image_shape : (int, int), optional
        (height, width) of frames in particle mode (default from the camera file).
    init_robot, init_heading, init_spheres : optional
        Particle mode: prior positions (m) and heading (rad) to start the filters;
        without them the first frame is searched for dark blobs.

    Ports
    -----
    inputs (raw/kalman): ``robot_meas`` (2,) m, ``heading_meas`` () rad, ``spheres_meas`` (N, 2) m, ``valid`` () bool
    inputs (particle): ``image`` (H, W) 1, ``valid`` () bool
    outputs: ``robot_est`` (2,) m, ``heading_est`` () rad, ``velocity_est`` (2,) m/s, ``spheres_est`` (N, 2) m,
    ``lost`` () bool
    """

    def __init__(self, name: str = "tracker", *, n_spheres: int = 1, mode: str = "kalman", predict_frames: int = 0,
                 on_loss: str = "hold", pixel_size: float | None = None, position_noise_px: float | None = None,
                 params: Params | None = None, image_shape: tuple[int, int] | None = None,
                 init_robot=None, init_heading: float = 0.0, init_spheres=None, dt: float = FRAME_PERIOD_S):
        if mode not in MODES:
            raise ParameterError(f"tracker {name!r}: mode {mode!r} is not one of {MODES}")
        if on_loss not in ("hold", "nan"):
            raise ParameterError(f"tracker {name!r}: on_loss {on_loss!r} must be 'hold' or 'nan'")
        if int(predict_frames) != predict_frames or predict_frames < 0:
            raise ParameterError(f"tracker {name!r}: predict_frames={predict_frames!r} must be a non-negative integer")
        params = camera_params() if params is None else params
        self.params = params
        tr = params.tracker
        self.mode, self.on_loss = mode, on_loss
        self.n_spheres = int(n_spheres)
        self.predict_frames = int(predict_frames)
        self.max_coast = int(tr.max_coast)
        self.pixel = float(params.camera.pixel_size if pixel_size is None else pixel_size)
        sigma_px = float(params.camera.position_noise if position_noise_px is None else position_noise_px)
        self.R = (sigma_px * self.pixel) ** 2 + self.pixel**2 / 12.0
        self.F, q_robot = cv_model(dt, tr.robot_accel_noise)
        _, q_sphere = cv_model(dt, tr.sphere_accel_noise)
        self.Q = np.stack([q_robot] + [q_sphere] * self.n_spheres)  # (M, 2, 2)
        n = self.n_spheres
        if mode == "particle":
            h, w = image_shape or (int(params.camera.height), int(params.camera.width))
            ins = [Port("image", (h, w), DIMENSIONLESS)]
            from magctl.sensing.particle_filter import ImageTracker

            self._pf_factory = lambda gen: ImageTracker(params, n_spheres=n, pixel=self.pixel, dt=dt,
                                                        init_robot=init_robot, init_heading=init_heading,
                                                        init_spheres=init_spheres, seed=gen)
        else:
            ins = [Port("robot_meas", (2,), "m"), Port("heading_meas", (), "rad"), Port("spheres_meas", (n, 2), "m")]
        ins.append(Port("valid", (), DIMENSIONLESS, "bool"))
        outs = [Port("robot_est", (2,), "m"), Port("heading_est", (), "rad"), Port("velocity_est", (2,), "m/s"),
                Port("spheres_est", (n, 2), "m"), Port("lost", (), DIMENSIONLESS, "bool")]
        super().__init__(name, inputs=ins, outputs=outs, dt=dt, feedthrough=True)

    # --- state ---------------------------------------------------------------------------------
    def state_vars(self):
        M, n = 1 + self.n_spheres, self.n_spheres
        out = [StateVar("x", (M, 2, 2), symbol="x̂", description="per object and axis [position m, velocity m/s]"),
               StateVar("P", (M, 2, 2), symbol="P", description="per object and axis covariance of x̂"),
               StateVar("heading", (), symbol="ψ̂", description="last measured heading, rad"),
               StateVar("init", (), "bool", description="the filter has had its first detection"),
               StateVar("missed", (), "int64", description="frames since the last valid detection"),
               StateVar("held_pos", (2,), symbol="p_h", description="robot estimate held while lost, m"),
               StateVar("held_sph", (n, 2), symbol="P_h", description="sphere estimates held while lost, m")]
        if self.mode == "particle":
            out.append(StateVar("pf", (), "object", description="one ImageTracker per trial (stepped on copies)",
                                batched=False))
        return tuple(out)

    def initial_state(self, batch, rng=None):
        M = 1 + self.n_spheres
        st = {"x": np.zeros((batch, M, 2, 2)), "P": np.zeros((batch, M, 2, 2)), "heading": np.zeros(batch),
              "init": np.zeros(batch, dtype=bool), "missed": np.zeros(batch, dtype=np.int64),
              "held_pos": np.zeros((batch, 2)), "held_sph": np.zeros((batch, self.n_spheres, 2))}
        if self.mode == "particle":
            gens = rng.generators if rng is not None else [np.random.default_rng(k) for k in range(batch)]
            st["pf"] = [self._pf_factory(g) for g in gens]
        return st

    @property
    def uses_random(self) -> bool:
        """Particle mode draws its particles from each trial's own stream."""
        return self.mode == "particle"

    # --- Kalman / raw --------------------------------------------------------------------------
    def kernel(self):
        """Raw and Kalman modes: :func:`magctl.sensing.kernels.tracker_step` (particle mode has no kernel)."""
        if self.mode == "particle":
            return None
        from magctl.sensing import kernels as k

        ahead = self.predict_frames * self.dt if self.mode == "kalman" else 0.0
        params = (self.mode == "kalman", self.on_loss == "nan", self.n_spheres, self.dt, float(self.R),
                  np.ascontiguousarray(self.F), np.ascontiguousarray(self.Q), START_VELOCITY_VAR, self.max_coast,
                  ahead)
        return Kernel(step=k.tracker_step, params=params)

    # --- particle mode: no kernel, Python ----------------------------------------------------------
    def step(self, state, u):
        """Raw and Kalman modes: the kernel (:meth:`Block.step`). Particle mode: each trial's filters stepped
        on copies of themselves, then the loss rules of the module docstring."""
        if self.mode != "particle":
            return super().step(state, u)
        pfs = [copy.deepcopy(pf) for pf in state["pf"]]  # the filters step in place: step copies
        pos, heading, vel, sph, found = self._particle(pfs, u)
        started = np.array([pf.started for pf in pfs], dtype=bool)
        missed = np.where(found, 0, state["missed"] + 1)
        lost = ~started | (missed > self.max_coast)
        new = dict(state) | {"pf": pfs, "heading": heading, "missed": missed}
        vel = np.where(lost[:, None], 0.0, vel)
        if self.on_loss == "hold":
            pos = np.where(lost[:, None], state["held_pos"], pos)
            sph = np.where(lost[:, None, None], state["held_sph"], sph)
            new |= {"held_pos": pos, "held_sph": sph}
        else:
            pos = np.where(lost[:, None], np.nan, pos)
            vel = np.where(lost[:, None], np.nan, vel)
            sph = np.where(lost[:, None, None], np.nan, sph)
            heading = np.where(lost, np.nan, heading)
        return {"robot_est": pos, "heading_est": heading, "velocity_est": vel, "spheres_est": sph, "lost": lost}, new

    def output(self, state, u):
        """``step``'s outputs (the kernel in raw and Kalman modes)."""
        return self.step(state, u)[0]

    def update(self, state, u):
        """``step``'s next state (the kernel in raw and Kalman modes)."""
        return self.step(state, u)[1]

    def _particle(self, pfs, u):
        b = u["image"].shape[0]
        pos, vel = np.zeros((b, 2)), np.zeros((b, 2))
        heading, found = np.zeros(b), np.zeros(b, dtype=bool)
        sph = np.zeros((b, self.n_spheres, 2))
        valid = np.asarray(u["valid"], dtype=bool)
        for i in range(b):  # image mode serves the rig (B = 1); each frame is a full image
            r = pfs[i].step(u["image"][i], bool(valid[i]))
            pos[i], heading[i], vel[i], sph[i], found[i] = r
        return pos, heading, vel, sph, found
