"""The 30 frames/s camera: sampling, processing latency, pixel quantisation, noise, dropped frames (paper §II).

Two modes share the sampling and latency model:

* ``"positions"`` (fast, for Monte Carlo) outputs what a perfect blob tracker
  would report: the robot position and each sphere centre, plus noise
  ``σ_px`` (pixels) and rounded to the pixel grid, and the robot heading with
  noise ``σ_θ``.
* ``"images"`` renders a grayscale frame (640 × 480 by default) of the robot's
  outline (:mod:`magctl.plant.outline`) and the spheres with optical blur and
  sensor noise (:func:`render_frame`), for the particle-filter tracker.

A frame sampled at step ``k`` is delivered at step ``k + latency`` (the image
processing lag, §VI-A). Before the first frame arrives, when the frame is
dropped (probability ``p_drop`` per frame, per-trial seeded stream) or when
the robot is outside the field of view, ``valid`` is false and the position
outputs repeat the last delivered value.

Pixel ``(row i, column j)`` has its centre at ``(x, y) = (j·s, i·s)`` with
``s`` the pixel size (7.5 µm, §VI-B), so a quantised coordinate is
``s·round(x/s)``.

Positions mode is implemented once, by the per-trial kernels of
:mod:`magctl.sensing.kernels` (both engines run them; the batched numpy form they
are tested against is in ``tests/reference/sensing_blocks.py``). Images mode has
no kernel and runs in Python.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy import ndimage

from magctl import FRAME_PERIOD_S
from magctl.config import Params, load_model, model_versions
from magctl.core.block import Block, StateVar, rng_var
from magctl.core.errors import ParameterError
from magctl.core.kernel import Kernel
from magctl.core.ports import DIMENSIONLESS, Port
from magctl.plant.fluid.params import sphere_params
from magctl.plant.outline import RobotOutline, robot_outline

MODES = ("positions", "images")


def camera_params() -> Params:
    """``models/camera.toml`` (tables ``camera``, ``render``, ``tracker``)."""
    return load_model("camera")


def view_span(width_px: int, height_px: int, pixel: float) -> tuple[float, float]:
    """Width and height [m] of a field of view whose pixel centres span ``[0, (W−1)·s] × [0, (H−1)·s]``."""
    return (int(width_px) - 1) * pixel, (int(height_px) - 1) * pixel


def field_of_view(params: Params | None = None) -> tuple[float, float]:
    """:func:`view_span` of the camera in ``models/camera.toml`` (a :class:`Camera` built from that file has the
    same :attr:`Camera.field_of_view`)."""
    c = (params if params is not None else camera_params()).camera
    return view_span(c.width, c.height, c.pixel_size)


def outside_view(points, span: tuple[float, float]) -> np.ndarray:
    """Which of ``points`` ``(..., 2)`` [m] lie outside the field of view ``span`` (``(w, h)``, origin at 0)."""
    p = np.asarray(points, dtype=float)
    return (p[..., 0] < 0) | (p[..., 0] > span[0]) | (p[..., 1] < 0) | (p[..., 1] > span[1])


# --- rendering --------------------------------------------------------------------------------
@dataclass(frozen=True)
class SeenShapes:
    """What the camera sees, in m: the robot's outline (:func:`magctl.plant.outline.robot_outline`) and the
    spheres' radius (``models/sphere.toml``), the plant's own statements of them."""

    robot: RobotOutline
    sphere_radius: float


@lru_cache(maxsize=8)
def _shapes_of(version: tuple) -> SeenShapes:
    return SeenShapes(robot_outline(), float(sphere_params().radius))


def seen_shapes() -> SeenShapes:
    """:class:`SeenShapes` of the current parameter set, read once per version of its files."""
    return _shapes_of(model_versions("robot_geometry.toml", "sphere.toml"))


def robot_sdf(x, y, position, heading, outline: RobotOutline):
    """Signed distance (negative inside) from points ``(x, y)`` to the robot's outline at ``position`` turned to
    ``heading``; lengths in the outline's units (m, or pixels for :meth:`RobotOutline.scaled` ones)."""
    c, s = np.cos(heading), np.sin(heading)
    dx, dy = np.asarray(x) - position[0], np.asarray(y) - position[1]
    return outline.signed_distance(c * dx + s * dy, -s * dx + c * dy)


def principal_axis(weight, x, y) -> tuple[float, float, float]:
    """Centroid ``(x̄, ȳ)`` of the weights ``weight`` at points ``(x, y)`` and the angle of their major principal
    axis, ``½ atan2(2 m_xy, m_xx − m_yy)`` of the weighted second central moments (rad, mod π, from +x towards
    +y): a blob's line in the image, whichever way its object faces."""
    w = np.asarray(weight, dtype=float)
    m = w.sum()
    cx, cy = (w * x).sum() / m, (w * y).sum() / m
    dx, dy = x - cx, y - cy
    mxx, myy, mxy = (w * dx * dx).sum() / m, (w * dy * dy).sum() / m, (w * dx * dy).sum() / m
    return float(cx), float(cy), 0.5 * math.atan2(2.0 * mxy, mxx - myy)


def _coverage(sdf, pixel):
    return np.clip(0.5 - sdf / pixel, 0.0, 1.0)


def render_frame(position, heading, spheres, render: Params, *, pixel: float, width: int, height: int,
                 noise: np.ndarray | None = None, shapes: SeenShapes | None = None) -> np.ndarray:
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
    shapes : SeenShapes, optional
        The robot's outline and the sphere radius; default :func:`seen_shapes`.
    """
    shapes = seen_shapes() if shapes is None else shapes
    radius = shapes.sphere_radius
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
        paint(sx, sy, radius, lambda x, y, sx=sx, sy=sy: np.hypot(x - sx, y - sy) - radius, render.sphere_level)
    pos = np.asarray(position, dtype=float)
    paint(pos[0], pos[1], shapes.robot.reach, lambda x, y: robot_sdf(x, y, pos, heading, shapes.robot),
          render.robot_level)
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
        self.shapes = seen_shapes()
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
        return view_span(self.width, self.height, self.pixel)

    def state_vars(self):
        L, n = self.latency, self.n_spheres
        out = [rng_var("pixel noise N(0, 1) and drop draws U[0, 1), read at position k"),
               StateVar("k", (), "int64", "k", "frames stepped (the stream position)", batched=False)]
        for j in range(L, 0, -1):  # the frames in the pipeline, oldest (delivered now) first
            ago = f"sampled {j} frames ago"
            out += [StateVar(f"pos{j}", (2,), symbol=f"p[k−{j}]", description=f"robot position {ago}, m"),
                    StateVar(f"head{j}", (), symbol=f"ψ[k−{j}]", description=f"heading {ago}, rad"),
                    StateVar(f"sph{j}", (n, 2), symbol=f"P_s[k−{j}]", description=f"spheres {ago}, m"),
                    StateVar(f"full{j}", (), "bool", description=f"a frame was {ago}")]
        if self.mode == "positions":
            out += [StateVar("meas_pos", (2,), symbol="p̃", description=self._meas_doc + ", robot, m"),
                    StateVar("meas_head", (), symbol="ψ̃", description=self._meas_doc + ", heading, rad"),
                    StateVar("meas_sph", (n, 2), symbol="P̃_s", description=self._meas_doc + ", spheres, m")]
            if L:
                out.append(StateVar("valid", (), "bool", description="the measurement delivered now is fresh"))
        return tuple(out)

    @property
    def _meas_doc(self) -> str:
        # with a lag the delivered frame depends on the state only: it is computed by update(), and
        # the state holds the frame delivered now; without one it holds the last frame delivered
        return "measurement delivered now" if self.latency else "last measurement delivered"

    def initial_state(self, batch, rng=None):
        L, n = self.latency, self.n_spheres
        pos, head, sph = self.primed if self.primed is not None else (np.zeros(2), 0.0, np.zeros((n, 2)))
        st = {"rng": rng, "k": 0}
        for j in range(L, 0, -1):
            st |= {f"pos{j}": np.broadcast_to(pos, (batch, 2)).copy(), f"head{j}": np.full(batch, head),
                   f"sph{j}": np.broadcast_to(sph, (batch, n, 2)).copy(),
                   f"full{j}": np.full(batch, self.primed is not None)}
        if self.mode == "positions":
            st |= {"meas_pos": np.zeros((batch, 2)), "meas_head": np.zeros(batch), "meas_sph": np.zeros((batch, n, 2))}
            if L:
                st["valid"] = np.zeros(batch, dtype=bool)  # no frame yet
                if self.primed is not None:
                    # running at rest: step −1 held the same frames and received the same one, and its update
                    # measured the frame delivered at step 0 (stream position 0)
                    at_rest = {"position": st["pos1"], "heading": st["head1"], "spheres": st["sph1"]}
                    st = self.update(st | {"k": -1}, at_rest)
        return st

    def kernel(self):
        """Positions mode: :mod:`magctl.sensing.kernels` (images mode renders frames: no kernel)."""
        if self.mode != "positions":
            return None
        from magctl.sensing import kernels as k

        fov_w, fov_h = self.field_of_view
        params = (self.n_spheres, self.pixel, self.pixel * self.sigma_px, self.sigma_heading, self.p_drop,
                  float(fov_w), float(fov_h))
        if self.latency:
            update = {1: k.camera_update_1, 2: k.camera_update_2}.get(self.latency, k.camera_update)
            return Kernel(output=k.camera_output, update=update, params=params, stream="rng")
        return Kernel(step=k.camera_step, params=params, stream="rng")

    # --- images mode: no kernel, Python ---------------------------------------------------------
    def output(self, state, u):
        """Positions mode: the kernel (:meth:`Block.output`). Images mode: the frame delivered now, rendered
        (blank when dropped), and ``valid`` when delivered with the robot in view."""
        if self.mode == "positions":
            return super().output(state, u)
        L = self.latency
        if L:
            pos, head, sph, full = state[f"pos{L}"], state[f"head{L}"], state[f"sph{L}"], state[f"full{L}"]
        else:
            pos, head, sph, full = u["position"], u["heading"], u["spheres"], np.ones(u["heading"].shape[0], bool)
        rng = state["rng"]
        delivered = full if rng is None else full & (rng.random((1,), at=state["k"])[:, 0] >= self.p_drop)
        fov_w, fov_h = self.field_of_view
        in_view = (pos[:, 0] >= 0) & (pos[:, 0] <= fov_w) & (pos[:, 1] >= 0) & (pos[:, 1] <= fov_h)
        return {"image": self._render(state, pos, head, sph, delivered), "valid": delivered & in_view}

    def update(self, state, u):
        """Positions mode: the kernel (:meth:`Block.update`). Images mode: the latency pipeline moves on by
        one frame (arrays passed along, never written)."""
        if self.mode == "positions":
            return super().update(state, u)
        new = {"rng": state["rng"], "k": state["k"] + 1}
        if self.latency:
            for j in range(self.latency, 1, -1):
                for x in ("pos", "head", "sph", "full"):
                    new[f"{x}{j}"] = state[f"{x}{j - 1}"]
            new |= {"pos1": u["position"], "head1": u["heading"], "sph1": u["spheres"],
                    "full1": np.ones(u["heading"].shape[0], dtype=bool)}
        return new

    def _render(self, state, pos, head, sph, delivered):
        rng = state["rng"]
        frames = np.empty((pos.shape[0], self.height, self.width))
        for b in range(pos.shape[0]):  # image mode runs rig-sized batches; rendering is per frame
            noise = None
            if rng is not None and self.params.render.noise_sigma > 0:
                noise = rng.large("standard_normal", b, (self.height, self.width), at=state["k"])
            frames[b] = render_frame(pos[b], head[b], sph[b], self.params.render, pixel=self.pixel,
                                     width=self.width, height=self.height, noise=noise, shapes=self.shapes)
            if not delivered[b]:
                frames[b] = self.params.render.background
        return frames
