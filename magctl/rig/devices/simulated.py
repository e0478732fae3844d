"""The simulated hardware: a physical world the coil board drives and a camera that films it.

The hardware-in-the-loop path of ``examples/lab-sim.toml`` is the real device path with two simulated ends:

* :class:`SimWorld` — the plant of the studies (:func:`magctl.rig.plant.build_sim_plant`, physics or stand-in)
  driven by what the coils carry: the coil board's outputs ``(dc, ac, freq)`` become the field command
  ``b = A i`` (:func:`~magctl.rig.devices.base.command_of`), one frame at a time;
* :class:`SimCamera` — a :class:`~magctl.rig.devices.base.Camera` that renders the world's true state
  (:func:`magctl.sensing.camera.render_frame`: blur, sensor noise) through the camera's own geometry (a
  :class:`~magctl.rig.devices.tracking.PixelCalibration`, which need not be the one the lab server believes),
  encodes and decodes every frame through OpenCV as a real camera's frames would arrive, stamps it and drops
  frames with the camera's drop probability (the frame numbers keep counting, so the drop shows).

Each :meth:`SimCamera.grab` first advances the world by one frame under the coils' outputs at that frame's time
(``coil_outputs(t)``: the host-compiled firmware behind its pseudo-terminal, its clock set to ``t`` in lock-step).
In real time the camera waits for its frame's time on the monotonic clock.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from magctl import FRAME_PERIOD_S
from magctl.config import Params, load_model
from magctl.rig.devices.base import Camera, CoilSetpoint, DeviceError, Frame, command_of, to_gray
from magctl.rig.interface import CoilMap
from magctl.rig.plant import Scene, build_sim_plant
from magctl.sensing.camera import camera_params, render_frame, seen_shapes

CoilOutputs = Callable[[float], CoilSetpoint]
"""What the coils carry at time t (s): the board's outputs, read at the board's own boundary."""


class SimWorld:
    """The plant with true state out, stepped one frame per call under the coils' outputs.

    Parameters
    ----------
    scene : Scene
        Where the robot and the spheres start.
    coils : CoilMap
        The actuator's allocation, to turn the board's currents back into the field they make.
    params : Params, optional
        ``models/rig.toml`` (its ``[physics]`` variability).
    plant : {"physics", "standin"}
    seed : int
    """

    def __init__(self, scene: Scene, coils: CoilMap, params: Params | None = None, plant: str = "physics",
                 seed: int = 0):
        self.scene, self.coils = scene, coils
        self.diagram = build_sim_plant(len(scene.spheres), scene, params or load_model("rig"), plant=plant,
                                       truth=True)
        self.state = self.diagram.initial_state(1, seed=seed)
        self.frame = 0
        self._read(self._inputs(CoilSetpoint.zero(coils.pinv.shape[0])))

    def _inputs(self, setpoint: CoilSetpoint) -> dict[str, np.ndarray]:
        cmd = command_of(setpoint, self.coils)
        return {"b_static": cmd.b_static[None, :], "b_osc": np.array([cmd.b_osc]), "freq": np.array([cmd.freq])}

    def _read(self, u) -> None:
        out = self.diagram.output(self.state, u)
        self.robot = np.array(out["robot_true"][0], dtype=float)
        self.heading = float(out["heading_true"][0])
        self.spheres = np.array(out["spheres_true"][0], dtype=float).reshape(-1, 2)

    def step(self, setpoint: CoilSetpoint) -> None:
        """One frame with the coils carrying ``setpoint``."""
        u = self._inputs(setpoint)
        _, self.state = self.diagram.step(self.state, u)
        self.frame += 1
        self._read(u)


class SimCamera(Camera):
    """Frames of a :class:`SimWorld`, rendered, encoded through OpenCV, stamped and sometimes dropped.

    Parameters
    ----------
    world : SimWorld
    coil_outputs : callable
        ``coil_outputs(t)``: the coils' outputs at time ``t`` s (the board's own report).
    geometry : PixelCalibration, optional
        Where the camera really looks (glass → pixels); ``models/camera.toml``'s 7.5 µm pixel, unrotated, by default.
    encoding : {"png", "jpg", "none"}
        How each frame travels (``cv2.imencode``/``imdecode``; jpg is lossy as a compressed stream is).
    realtime : bool
        Deliver frames at the frame rate on the monotonic clock (else one frame per :meth:`grab`).
    drop_probability : float
        Per frame; ``models/camera.toml`` by default.
    brightness : callable, optional
        ``brightness(frame_number)`` multiplies the image (a lighting change).
    stops_after_frame : int, optional
        The camera delivers nothing after this frame number (a camera that stops, for fault drills); the world
        goes on.
    """

    def __init__(self, world: SimWorld, coil_outputs: CoilOutputs, *, geometry=None, encoding: str = "png",
                 realtime: bool = False, period: float = FRAME_PERIOD_S, drop_probability: float | None = None,
                 seed: int = 0, brightness: Callable[[int], float] | None = None, stops_after_frame: int | None = None,
                 name: str = "sim-camera"):
        from magctl.rig.devices.tracking import PixelCalibration

        if encoding not in ("png", "jpg", "none"):
            raise DeviceError(name, f"encoding {encoding!r} is not png, jpg or none")
        self.world, self.coil_outputs, self.encoding, self.realtime = world, coil_outputs, encoding, realtime
        self.period, self.name, self.brightness = float(period), name, brightness
        self.stops_after_frame = stops_after_frame
        self.params = camera_params()
        self.shapes = seen_shapes()
        self.geometry = geometry if geometry is not None else PixelCalibration.identity()
        cam = self.params.camera
        self.width, self.height = int(cam.width), int(cam.height)
        self.drop_probability = float(cam.drop_probability if drop_probability is None else drop_probability)
        self._rng = np.random.default_rng([seed, 0x5CA3])
        self._open = False
        self.number = 0

    @property
    def shape(self) -> tuple[int, int]:
        return self.height, self.width

    def open(self) -> None:
        if self.encoding != "none":
            import cv2  # noqa: F401 - the encode path needs OpenCV: fail at open, not at the first frame
        self._t0 = time.monotonic()
        self._open = True

    def close(self) -> None:
        self._open = False

    def _image(self) -> np.ndarray:
        """The world as this camera sees it: true state → its pixels → rendered with blur and noise."""
        w, g = self.world, self.geometry
        s = g.pixel_size
        robot_px = g.to_pixels(w.robot[None, :])[0]
        ahead_px = g.to_pixels((w.robot + 1e-4 * np.array([np.cos(w.heading), np.sin(w.heading)]))[None, :])[0]
        heading = float(np.arctan2(*(ahead_px - robot_px)[::-1]))
        spheres = g.to_pixels(w.spheres) * s if len(w.spheres) else np.zeros((0, 2))
        noise = self._rng.standard_normal((self.height, self.width), dtype=np.float32)
        img = render_frame(robot_px * s, heading, spheres, self.params.render, pixel=s, width=self.width,
                           height=self.height, noise=noise, shapes=self.shapes)
        if self.brightness is not None:
            img = img * float(self.brightness(self.number))
        return np.clip(img, 0.0, 1.0)

    def _transport(self, img: np.ndarray) -> np.ndarray:
        if self.encoding == "none":
            return img
        import cv2

        raw = np.round(img * 255.0).astype(np.uint8)
        ok, buf = cv2.imencode("." + self.encoding, raw)
        if not ok:
            raise DeviceError(self.name, f"OpenCV could not encode a frame as {self.encoding}")
        return to_gray(cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE))

    def grab(self, timeout: float) -> Frame | None:
        """The next frame: the world advanced one frame under the coils' outputs, then filmed. A dropped frame
        returns None (the world still moved; the next frame's number shows the gap)."""
        if not self._open:
            raise DeviceError(self.name, "camera is not open")
        t = (self.number + 1) * self.period
        if self.realtime:
            wait = self._t0 + t - time.monotonic()
            if wait > timeout:
                time.sleep(max(timeout, 0.0))
                return None
            if wait > 0:
                time.sleep(wait)
        self.world.step(self.coil_outputs(t))
        self.number += 1
        if self._rng.random() < self.drop_probability:
            return None
        if self.stops_after_frame is not None and self.number > self.stops_after_frame:
            return None
        return Frame(self._transport(self._image()), t, self.number)
