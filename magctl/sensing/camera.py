"""The 30 frames/s camera: sampling, processing latency, pixel quantisation, noise, dropped frames (paper §II).

Two modes share the sampling and latency model:

* ``"positions"`` (fast, for Monte Carlo) outputs what a perfect blob tracker
  would report: the robot position and each sphere centre, plus noise
  ``σ_px`` (pixels) and rounded to the pixel grid, and the robot heading with
  noise ``σ_θ``.
* ``"images"`` renders a grayscale frame (640 × 480 by default) of the robot
  outline and the spheres with optical blur and sensor noise
  (:func:`render_frame`), for the particle-filter tracker.

A frame sampled at step ``k`` is delivered at step ``k + latency`` (the image
processing lag, §VI-A). Before the first frame arrives, when the frame is
dropped (probability ``p_drop`` per frame, per-trial seeded stream) or when
the robot is outside the field of view, ``valid`` is false and the position
outputs repeat the last delivered value.

Pixel ``(row i, column j)`` has its centre at ``(x, y) = (j·s, i·s)`` with
``s`` the pixel size (7.5 µm, §VI-B), so a quantised coordinate is
``s·round(x/s)``.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from magctl import FRAME_PERIOD_S
from magctl.config import Params, load_model
from magctl.core.block import Block
from magctl.core.errors import ParameterError
from magctl.core.ports import DIMENSIONLESS, Port

MODES = ("positions", "images")


def camera_params() -> Params:
    """``models/camera.toml`` (tables ``camera``, ``render``, ``tracker``)."""
    return load_model("camera")


def quantise(x: np.ndarray, pixel: float) -> np.ndarray:
    """Round coordinates (m) to the nearest pixel centre: ``s·round(x/s)``."""
    return pixel * np.round(x / pixel)


# --- rendering --------------------------------------------------------------------------------
def _box_sdf(px, py, half_l, half_w):
    qx, qy = np.abs(px) - half_l, np.abs(py) - half_w
    outside = np.hypot(np.maximum(qx, 0.0), np.maximum(qy, 0.0))
    return outside + np.minimum(np.maximum(qx, qy), 0.0)


def robot_sdf(x, y, position, heading, length, width, notch):
    """Signed distance (m, negative inside) to the robot outline.

    A ``length × width`` rectangle along ``heading`` with a disc of radius ``notch``
    cut from the centre of its front edge: a simplified outline of the star-shaped
    robot with its concave front face (paper §II, Fig. 1).
    """
    c, s = np.cos(heading), np.sin(heading)
    dx, dy = x - position[0], y - position[1]
    px, py = c * dx + s * dy, -s * dx + c * dy
    body = _box_sdf(px, py, length / 2, width / 2)
    cut = np.hypot(px - length / 2, py) - notch
    return np.maximum(body, -cut)


def _coverage(sdf, pixel):
    return np.clip(0.5 - sdf / pixel, 0.0, 1.0)


def render_frame(position, heading, spheres, render: Params, *, pixel: float, width: int, height: int,
                 noise: np.ndarray | None = None) -> np.ndarray:
    """One grayscale frame (height × width, values in [0, 1]) of the robot and the spheres.

    Objects are drawn with anti-aliased edges (area coverage from the signed
    distance), darkening a uniform background; the frame is blurred with a
    Gaussian of ``blur_sigma`` pixels and ``noise_sigma · noise`` is added.

    Parameters
    ----------
    position : (2,) array, m
    heading : float, rad
    spheres : (N, 2) array, m
    render : Params
        The ``[render]`` table of ``models/camera.toml``.
    noise : (height, width) array, optional
        Standard normal draws; no noise when None.
    """
    img = np.full((height, width), render.background)
    margin = 4 * max(render.blur_sigma, 1.0) + 2

    def paint(cx, cy, radius, sdf_fn, level):
        j0, j1 = int(np.floor(cx / pixel - radius / pixel - margin)), int(np.ceil(cx / pixel + radius / pixel + margin))
        i0, i1 = int(np.floor(cy / pixel - radius / pixel - margin)), int(np.ceil(cy / pixel + radius / pixel + margin))
        j0, i0, j1, i1 = max(j0, 0), max(i0, 0), min(j1, width - 1), min(i1, height - 1)
        if j1 < j0 or i1 < i0:
            return
        yy, xx = np.mgrid[i0:i1 + 1, j0:j1 + 1] * pixel
        cov = _coverage(sdf_fn(xx, yy), pixel)
        win = img[i0:i1 + 1, j0:j1 + 1]
        win += cov * (level - win)

    for sx, sy in np.asarray(spheres, dtype=float).reshape(-1, 2):
        paint(sx, sy, render.sphere_radius,
              lambda x, y, sx=sx, sy=sy: np.hypot(x - sx, y - sy) - render.sphere_radius, render.sphere_level)
    pos = np.asarray(position, dtype=float)
    reach = np.hypot(render.robot_length, render.robot_width) / 2
    dims = (render.robot_length, render.robot_width, render.robot_notch_radius)
    paint(pos[0], pos[1], reach, lambda x, y: robot_sdf(x, y, pos, heading, *dims), render.robot_level)
    if render.blur_sigma > 0:
        img = ndimage.gaussian_filter(img, render.blur_sigma, mode="nearest")
    if noise is not None:
        img = img + render.noise_sigma * noise
    return img


# --- the block --------------------------------------------------------------------------------
class Camera(Block):
    """Camera block (see the module docstring for the model).

    Parameters
    ----------
    name : str
    n_spheres : int
        Number of spheres N on the ``spheres`` input.
    mode : {"positions", "images"}
    latency_frames : int, optional
        Processing latency in frames (default from ``models/camera.toml``).
    position_noise_px, heading_noise, drop_probability : float, optional
        Overrides of the file's values (pixels, rad, probability per frame).
    pixel_size : float, optional
        Pixel size in m.
    params : Params, optional
        Parsed ``models/camera.toml``.
    primed : (position, heading, spheres), optional
        The camera was already running with the plant at rest in this state: the
        latency pipeline starts full of valid frames of it instead of empty.

    Ports
    -----
    inputs: ``position`` (2,) m, ``heading`` () rad, ``spheres`` (N, 2) m
    outputs (positions): ``robot_meas`` (2,) m, ``heading_meas`` () rad, ``spheres_meas`` (N, 2) m, ``valid`` () bool
    outputs (images): ``image`` (H, W) 1, ``valid`` () bool
    """

    def __init__(self, name: str = "camera", *, n_spheres: int = 1, mode: str = "positions",
                 latency_frames: int | None = None, position_noise_px: float | None = None,
                 heading_noise: float | None = None, drop_probability: float | None = None,
                 pixel_size: float | None = None, params: Params | None = None, primed=None,
                 dt: float = FRAME_PERIOD_S):
        if mode not in MODES:
            raise ParameterError(f"camera {name!r}: mode {mode!r} is not one of {MODES}")
        if int(n_spheres) != n_spheres or n_spheres < 0:
            raise ParameterError(f"camera {name!r}: n_spheres={n_spheres!r} must be a non-negative integer")
        params = camera_params() if params is None else params
        cam = params.camera
        self.params = params
        self.mode = mode
        self.n_spheres = int(n_spheres)
        self.latency = int(cam.latency if latency_frames is None else latency_frames)
        if self.latency != (cam.latency if latency_frames is None else latency_frames) or self.latency < 0:
            raise ParameterError(f"camera {name!r}: latency_frames={latency_frames!r} must be a non-negative integer")
        self.pixel = float(cam.pixel_size if pixel_size is None else pixel_size)
        self.width, self.height = int(cam.width), int(cam.height)
        self.sigma_px = float(cam.position_noise if position_noise_px is None else position_noise_px)
        self.sigma_heading = float(cam.heading_noise if heading_noise is None else heading_noise)
        self.p_drop = float(cam.drop_probability if drop_probability is None else drop_probability)
        if self.pixel <= 0 or self.sigma_px < 0 or self.sigma_heading < 0 or not 0 <= self.p_drop < 1:
            raise ParameterError(
                f"camera {name!r}: need pixel_size > 0, noise ≥ 0 and 0 ≤ drop_probability < 1 "
                f"(got {self.pixel}, {self.sigma_px}, {self.sigma_heading}, {self.p_drop})")
        n = self.n_spheres
        self.primed = None
        if primed is not None:
            p_pos, p_head, p_sph = primed
            self.primed = (np.asarray(p_pos, dtype=float).reshape(2), float(p_head),
                           np.asarray(p_sph, dtype=float).reshape(n, 2))
        ins = [Port("position", (2,), "m"), Port("heading", (), "rad"), Port("spheres", (n, 2), "m")]
        if mode == "positions":
            outs = [Port("robot_meas", (2,), "m"), Port("heading_meas", (), "rad"), Port("spheres_meas", (n, 2), "m")]
        else:
            outs = [Port("image", (self.height, self.width), DIMENSIONLESS)]
        outs.append(Port("valid", (), DIMENSIONLESS, "bool"))
        super().__init__(name, inputs=ins, outputs=outs, dt=dt, feedthrough=self.latency == 0)

    @property
    def uses_random(self) -> bool:
        return True

    @property
    def field_of_view(self) -> tuple[float, float]:
        """Width and height of the field of view in m (pixel centres span ``[0, (W−1)·s]``)."""
        return (self.width - 1) * self.pixel, (self.height - 1) * self.pixel

    def initial_state(self, batch, rng=None):
        L, n = self.latency, self.n_spheres
        st = {"rng": rng, "head": 0,
              "buf_pos": np.zeros((L, batch, 2)), "buf_head": np.zeros((L, batch)),
              "buf_sph": np.zeros((L, batch, n, 2)), "buf_full": np.zeros((L, batch), dtype=bool)}
        if self.primed is not None:
            st["buf_pos"][:], st["buf_head"][:], st["buf_sph"][:] = self.primed
            st["buf_full"][:] = True
        if self.mode == "positions":
            st["last"] = (np.zeros((batch, 2)), np.zeros(batch), np.zeros((batch, n, 2)))
        return st

    def _sample(self, state, u):
        """The true plant state of the frame delivered now, and whether one exists."""
        if self.latency == 0:
            b = u["position"].shape[0]
            return u["position"], u["heading"], u["spheres"], np.ones(b, dtype=bool)
        h = state["head"]
        return state["buf_pos"][h], state["buf_head"][h], state["buf_sph"][h], state["buf_full"][h]

    def _draws(self, state, batch):
        # one step's draws, cached so output() is repeatable within a step; cleared by update()
        d = state.get("draws")
        if d is None:
            rng = state["rng"]
            n = self.n_spheres
            if rng is None:
                d = (np.zeros((batch, 3 + 2 * n)), np.ones((batch, 1)))
            else:
                d = (rng.standard_normal((3 + 2 * n,)), rng.random((1,)))
            state["draws"] = d
        return d

    def output(self, state, u):
        if self.latency and self.mode == "positions":
            # with a lag the frame delivered now depends on the state only: compute it once per step
            out = state.get("out")
            if out is None:
                out = state["out"] = self._output(state, u)
            return out
        return self._output(state, u)

    def _output(self, state, u):
        pos, head, sph, full = self._sample(state, u)
        b = pos.shape[0]
        normal, uniform = self._draws(state, b)
        delivered = full & (uniform[:, 0] >= self.p_drop)
        fov_w, fov_h = self.field_of_view
        in_view = (pos[:, 0] >= 0) & (pos[:, 0] <= fov_w) & (pos[:, 1] >= 0) & (pos[:, 1] <= fov_h)
        if self.mode == "images":
            frames = state.get("frame")
            if frames is None:
                frames = state["frame"] = self._render(state, pos, head, sph, delivered)
            return {"image": frames, "valid": delivered & in_view}
        valid = delivered & in_view
        s = self.pixel
        n = self.n_spheres
        robot = quantise(pos + s * self.sigma_px * normal[:, :2], s)
        heading = np.angle(np.exp(1j * (head + self.sigma_heading * normal[:, 2])))
        spheres = quantise(sph + s * self.sigma_px * normal[:, 3:].reshape(b, n, 2), s)
        last_r, last_h, last_s = state["last"]
        return {
            "robot_meas": np.where(valid[:, None], robot, last_r),
            "heading_meas": np.where(valid, heading, last_h),
            "spheres_meas": np.where(valid[:, None, None], spheres, last_s),
            "valid": valid,
        }

    def _render(self, state, pos, head, sph, delivered):
        rng = state["rng"]
        frames = np.empty((pos.shape[0], self.height, self.width))
        for b in range(pos.shape[0]):  # image mode runs rig-sized batches; rendering is per frame
            # whole-frame noise is drawn straight from the trial's generator: chunking it would hold
            # hundreds of frames in memory
            noise = None
            if rng is not None and self.params.render.noise_sigma > 0:
                noise = rng.generators[b].standard_normal((self.height, self.width))
            frames[b] = render_frame(pos[b], head[b], sph[b], self.params.render, pixel=self.pixel,
                                     width=self.width, height=self.height, noise=noise)
            if not delivered[b]:
                frames[b] = self.params.render.background
        return frames

    def update(self, state, u):
        if self.mode == "positions":
            out = self.output(state, u)
            state["last"] = (out["robot_meas"], out["heading_meas"], out["spheres_meas"])
        state.pop("draws", None)
        state.pop("frame", None)
        state.pop("out", None)
        if self.latency:
            h = state["head"]
            state["buf_pos"][h] = u["position"]
            state["buf_head"][h] = u["heading"]
            state["buf_sph"][h] = u["spheres"]
            state["buf_full"][h] = True
            state["head"] = (h + 1) % self.latency
        return state
