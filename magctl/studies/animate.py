"""Animated GIFs of simulated pushes: robot outline, spheres, goal, trail and time stamp.

Trajectories come in SI (m, rad, s) for one trial, e.g. ``res["position"][k]``
from :func:`magctl.core.simulate`; the drawing is in µm. Frames are rendered
with matplotlib's Agg canvas and written by pillow with one shared palette, so
a few hundred frames stay well under 2 MB.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Circle, Polygon
from PIL import Image

from magctl.core.errors import MagctlError
from magctl.core.units import UM_PER_M
from magctl.plant.fluid.params import sphere_params
from magctl.plant.outline import robot_outline

MAX_FRAMES = 150
"""Default cap on frames per GIF: keeps files small whatever the trajectory length."""


class AnimationError(MagctlError, ValueError):
    """Trajectories or options handed to :func:`animate_push` are malformed; the message names the argument."""


def frame_indices(n_steps: int, stride: int) -> np.ndarray:
    """Steps drawn: every ``stride``-th from the first, plus the last so the final state is shown."""
    idx = np.arange(0, n_steps, stride)
    if idx[-1] != n_steps - 1:
        idx = np.append(idx, n_steps - 1)
    return idx


def default_stride(t: np.ndarray, fps: float, max_frames: int = MAX_FRAMES) -> int:
    """Real-time playback at ``fps`` when that fits in ``max_frames`` frames, faster otherwise."""
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 1.0 / fps
    real_time = max(1, round(1.0 / (fps * dt)))
    return max(real_time, math.ceil(len(t) / max(1, max_frames - 1)))


def _array(name: str, value, shape: tuple, what: str) -> np.ndarray:
    """``value`` as a finite float array of ``shape`` (None entries are free), or AnimationError."""
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise AnimationError(f"{name} must be a numeric array {what}, got {type(value).__name__}") from None
    if arr.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, arr.shape)):
        raise AnimationError(f"{name} must have shape {what}, got {arr.shape}")
    if not np.isfinite(arr).all():
        raise AnimationError(f"{name} holds NaN or infinite values")
    return arr


def _check_metres(name: str, arr: np.ndarray) -> None:
    if arr.size and np.abs(arr).max() > 0.1:
        raise AnimationError(f"{name} must be in metres: |values| up to {np.abs(arr).max():.3g} look like µm")


def _validate(t, robot_xy, robot_heading, spheres_xy, goal, outline, fps, stride):
    t = _array("t", t, (None,), "(T,) in s")
    n = len(t)
    if n == 0:
        raise AnimationError("t is empty: nothing to animate")
    if n > 1 and not (np.diff(t) > 0).all():
        raise AnimationError("t must be strictly increasing")
    robot_xy = _array("robot_xy", robot_xy, (n, 2), f"(T, 2) = ({n}, 2) in m")
    robot_heading = _array("robot_heading", robot_heading, (n,), f"(T,) = ({n},) in rad")
    spheres_xy = _array("spheres_xy", spheres_xy, (n, None, 2), f"(T, N, 2) = ({n}, N, 2) in m")
    if goal is not None:
        shape = (2,) if np.ndim(goal) == 1 else (n, 2)
        goal = np.broadcast_to(_array("goal", goal, shape, f"(2,) or (T, 2) = ({n}, 2) in m"), (n, 2))
    outline = robot_outline().vertices if outline is None else _array("outline", outline, (None, 2), "(P, 2) in m")
    if len(outline) < 3:
        raise AnimationError(f"outline needs at least 3 vertices, got {len(outline)}")
    for name, arr in (("robot_xy", robot_xy), ("spheres_xy", spheres_xy), ("goal", goal), ("outline", outline)):
        if arr is not None:
            _check_metres(name, arr)
    if not (isinstance(fps, (int, float)) and math.isfinite(fps) and fps > 0):
        raise AnimationError(f"fps must be a positive number, got {fps!r}")
    if stride is not None and (isinstance(stride, bool) or int(stride) != stride or stride < 1):
        raise AnimationError(f"stride must be a positive integer, got {stride!r}")
    return t, robot_xy, robot_heading, spheres_xy, goal, outline


def _extent(robot_xy, spheres_xy, goal, outline, radius, margin=80e-6):
    """Square view (µm) holding the robot, spheres and goal over the whole run."""
    reach = np.abs(outline).max()
    pts = [robot_xy - reach, robot_xy + reach]
    if spheres_xy.size:
        flat = spheres_xy.reshape(-1, 2)
        pts += [flat - radius, flat + radius]
    if goal is not None:
        pts.append(goal)
    allp = np.concatenate(pts)
    lo, hi = allp.min(axis=0) - margin, allp.max(axis=0) + margin
    c, half = (lo + hi) / 2, (hi - lo).max() / 2
    return (c - half) * 1e6, (c + half) * 1e6


def animate_push(t, robot_xy, robot_heading, spheres_xy, path, *, goal=None, outline=None, fps: float = 15,
                 stride: int | None = None, trail: bool = True, title: str | None = None,
                 sphere_radius: float | None = None, max_frames: int = MAX_FRAMES, size_px: int = 360) -> Path:
    """Write a GIF of one push trial.

    Parameters
    ----------
    t : array, shape (T,)
        Time of each step in s.
    robot_xy : array, shape (T, 2)
        Robot centre in m.
    robot_heading : array, shape (T,)
        Robot heading in rad (direction of the outline's +x axis).
    spheres_xy : array, shape (T, N, 2)
        Sphere centres in m (N may be 0).
    path : str or Path
        Output file (``.gif``); parent folders are created.
    goal : array, shape (2,) or (T, 2), optional
        Goal of the pushed sphere in m, drawn as a cross.
    outline : array, shape (P, 2), optional
        Robot outline in the robot frame, m; default the robot's own
        (:func:`magctl.plant.outline.robot_outline`, 310 µm along the heading, 480 µm across).
    fps : float
        Playback frame rate.
    stride : int, optional
        Draw every ``stride``-th step (the last step is always drawn); default
        real time at ``fps``, coarser when that would exceed ``max_frames``.
    trail : bool
        Draw the robot's path so far.
    title : str, optional
        Text above the plot.
    sphere_radius : float, optional
        Sphere radius in m; default ``models/sphere.toml`` (the paper's 105 µm).
    max_frames : int
        Cap on frames when ``stride`` is not given.
    size_px : int
        Width and height of the GIF in pixels.

    Returns
    -------
    Path
        The GIF written.
    """
    t, robot_xy, robot_heading, spheres_xy, goal, outline = _validate(
        t, robot_xy, robot_heading, spheres_xy, goal, outline, fps, stride)
    sphere_radius = sphere_params().radius if sphere_radius is None else sphere_radius
    if not (isinstance(sphere_radius, (int, float)) and math.isfinite(sphere_radius) and 0 < sphere_radius < 0.1):
        raise AnimationError(f"sphere_radius must be a positive length in metres, got {sphere_radius!r}")
    stride = int(stride) if stride is not None else default_stride(t, fps, max_frames)
    frames = frame_indices(len(t), stride)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)

    dpi = 80
    fig = Figure(figsize=(size_px / dpi, size_px / dpi), dpi=dpi)
    canvas = FigureCanvasAgg(fig)
    ax = fig.add_axes((0.17, 0.11, 0.8, 0.8))
    lo, hi = _extent(robot_xy, spheres_xy, goal, outline, sphere_radius)
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.set_xlabel("x (µm)")
    ax.set_ylabel("y (µm)")
    ax.set_facecolor("#f4f1e8")  # the oil-covered glass
    if title:
        fig.suptitle(title, fontsize=9, y=0.99)

    # moving artists are drawn over a saved background (blitting): the axes are rendered only once
    (trail_line,) = ax.plot([], [], color="#c0392b", lw=0.8, alpha=0.7, animated=True)
    spheres = [ax.add_patch(Circle((0, 0), sphere_radius * UM_PER_M, fc="#d9e7f5", ec="#2b5d8a", lw=1.0, animated=True))
               for _ in range(spheres_xy.shape[1])]
    robot = ax.add_patch(Polygon(outline * UM_PER_M, closed=True, fc="#555555", ec="black", lw=0.8, animated=True))
    (arrow,) = ax.plot([], [], color="white", lw=1.5, solid_capstyle="round", animated=True)
    nose = np.array([[0.0, 0.0], [0.8 * outline[:, 0].max(), 0.0]])  # heading marker, as the paper's figures
    (goal_mark,) = ax.plot([], [], "x", color="#1e8449", ms=9, mew=2, animated=True)
    stamp = ax.text(0.02, 0.97, "", transform=ax.transAxes, va="top", fontsize=9, family="monospace", animated=True)
    moving = [trail_line, *spheres, robot, arrow, goal_mark, stamp]
    canvas.draw()
    background = canvas.copy_from_bbox(fig.bbox)

    def render(k: int) -> Image.Image:
        rot = np.array([[math.cos(robot_heading[k]), math.sin(robot_heading[k])],
                        [-math.sin(robot_heading[k]), math.cos(robot_heading[k])]])
        robot.set_xy((outline @ rot + robot_xy[k]) * UM_PER_M)
        arrow.set_data(*((nose @ rot + robot_xy[k]) * UM_PER_M).T)
        for circ, xy in zip(spheres, spheres_xy[k]):
            circ.set_center(xy * UM_PER_M)
        if trail:
            trail_line.set_data(robot_xy[: k + 1, 0] * UM_PER_M, robot_xy[: k + 1, 1] * UM_PER_M)
        if goal is not None:
            goal_mark.set_data([goal[k, 0] * UM_PER_M], [goal[k, 1] * UM_PER_M])
        stamp.set_text(f"t = {t[k]:6.2f} s")
        canvas.restore_region(background)
        for artist in moving:
            ax.draw_artist(artist)
        return Image.fromarray(np.asarray(canvas.buffer_rgba())[..., :3])

    # one palette for all frames, taken from the last (it holds every colour, the full trail included):
    # colours never flicker and unchanged pixels compress away
    palette = render(frames[-1]).quantize(colors=128, method=Image.Quantize.MEDIANCUT)
    images = [render(k).quantize(palette=palette, dither=Image.Dither.NONE) for k in frames]
    images[0].save(path, save_all=True, append_images=images[1:], duration=round(1000 / fps), loop=0,
                   optimize=False)
    return path
