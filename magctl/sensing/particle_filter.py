"""Particle filters on the image gradient for the robot pose and the spheres (paper §II, ref [21]).

Each object has a contour model: points ``c_k`` on its outline with outward
normals ``n_k`` (a circle of the sphere radius; the robot's own outline,
:mod:`magctl.plant.outline`, as :func:`magctl.sensing.camera.render_frame` draws it). A
dark object on a bright background has an image gradient pointing outward
across its edge, so a particle (pose hypothesis) is scored by the mean edge
strength along its contour::

    s = (1/K) Σ_k ∇I(c_k) · n_k / s_ref

normalised by ``s_ref``, the score of the true pose on a clean frame. Weights
are ``w ∝ exp((s − max s)/τ)``; the estimate is the weighted mean (circular
mean for the heading). Particles are resampled systematically when the
effective number ``1/Σw²`` falls below half (the algorithm of
:func:`filterpy.monte_carlo.systematic_resample`, its random offset drawn from
the tracker's own seeded stream rather than NumPy's global one, so that a seeded
tracker is reproducible). The gradient is computed only in a window around
each particle cloud. An object whose estimate scores below
``edge_threshold`` is not detected this frame; its particles then diffuse
further each missed frame to re-acquire it. A frame without an image
(``valid`` false: dropped) is not a miss of that kind: it only advances the
motion model by one frame of the ordinary diffusion. The robot's outline is
symmetric under a half turn but for its notch, so each frame the half-turned
estimate, slid along its axis, is scored too and kept (the cloud moved with it)
when it scores higher: a cloud that settled on a turned pose would never
diffuse back.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from magctl.config import Params
from magctl.core.errors import MagctlError
from magctl.plant.outline import RobotOutline
from magctl.sensing.camera import SeenShapes, principal_axis, render_frame, robot_sdf, seen_shapes


class DetectionError(MagctlError):
    """The first frame does not show the objects the tracker was asked to find."""


def sphere_contour(radius: float, k: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """Points (K, 2) on a circle of ``radius`` and their outward normals."""
    a = np.linspace(0, 2 * np.pi, k, endpoint=False)
    n = np.stack([np.cos(a), np.sin(a)], axis=1)
    return radius * n, n


def robot_contour(outline: RobotOutline, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Points (K, 2) on the robot's outline in its own frame (x along the heading), about ``spacing`` apart on each
    edge, and their outward normals; in the outline's units."""
    v = outline.vertices
    pts, nrm = [], []
    for p0, p1 in zip(v, np.roll(v, -1, axis=0), strict=True):
        d = p1 - p0
        length = float(np.hypot(*d))
        m = max(1, int(round(length / spacing)))
        t = (np.arange(m) + 0.5) / m
        pts.append(p0 + t[:, None] * d)
        nrm.append(np.broadcast_to(np.array([d[1], -d[0]]) / length, (m, 2)))   # outward of a counter-clockwise loop
    return np.vstack(pts), np.vstack(nrm)


def systematic_resample(weights: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Indices of a systematic resample of ``weights`` (summing to 1): ``N`` positions ``(u + k)/N`` with one
    offset ``u ~ U[0, 1)`` drawn from ``rng``, each mapped to the first particle whose cumulative weight exceeds it
    (as :func:`filterpy.monte_carlo.systematic_resample`, which draws ``u`` from NumPy's global generator)."""
    n = len(weights)
    positions = (rng.random() + np.arange(n)) / n
    return np.minimum(np.searchsorted(np.cumsum(weights), positions, side="right"), n - 1)


MIN_SEEN = 0.2
"""Smallest fraction of an object's contour in view for its pose to be scored."""
OCCLUSION_MARGIN_PX = 2.0
"""Contour points within this distance of the robot's outline are hidden (the blurred edge of the darker robot)."""


class _ObjectFilter:
    """One object's particles ``(P, 3)``: x, y (pixels) and heading (rad)."""

    def __init__(self, pts, nrm, oriented, n_particles, sigma_px, sigma_heading, tau, rng):
        self.pts, self.nrm, self.oriented = pts, nrm, oriented
        self.n = n_particles
        self.sigma_px, self.sigma_heading, self.tau = sigma_px, sigma_heading, tau
        self.rng = rng
        self.reach = float(np.max(np.hypot(pts[:, 0], pts[:, 1]))) + 3.0
        self.particles = np.zeros((n_particles, 3))
        self.weights = np.full(n_particles, 1.0 / n_particles)
        self.estimate = np.zeros(3)
        self.velocity = np.zeros(2)
        self.missed = 0
        self.searched = 0  # valid frames without a detection: they, not frames without an image, widen the search
        self.s_ref = 1.0
        self.occluder = None
        """``occluder(px, py) -> bool array``: contour points hidden behind another object (not scored)."""

    def reset(self, x, y, heading, spread_px=1.0):
        self.particles[:, 0] = x + spread_px * self.rng.standard_normal(self.n)
        self.particles[:, 1] = y + spread_px * self.rng.standard_normal(self.n)
        self.particles[:, 2] = heading + (self.sigma_heading * self.rng.standard_normal(self.n) if self.oriented else 0)
        self.weights[:] = 1.0 / self.n
        self.estimate = np.array([x, y, heading], dtype=float)

    def scores(self, image, poses):
        """Normalised edge score of each pose (M, 3) on ``image`` (pixels)."""
        c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
        px = poses[:, None, 0] + c[:, None] * self.pts[None, :, 0] - s[:, None] * self.pts[None, :, 1]
        py = poses[:, None, 1] + s[:, None] * self.pts[None, :, 0] + c[:, None] * self.pts[None, :, 1]
        nx = c[:, None] * self.nrm[None, :, 0] - s[:, None] * self.nrm[None, :, 1]
        ny = s[:, None] * self.nrm[None, :, 0] + c[:, None] * self.nrm[None, :, 1]
        h, w = image.shape
        j0 = int(max(np.floor(px.min()) - 2, 0))
        j1 = int(min(np.ceil(px.max()) + 3, w))
        i0 = int(max(np.floor(py.min()) - 2, 0))
        i1 = int(min(np.ceil(py.max()) + 3, h))
        if j1 - j0 < 3 or i1 - i0 < 3:
            return np.zeros(len(poses))
        crop = image[i0:i1, j0:j1]
        gy, gx = np.gradient(crop)
        coords = np.stack([(py - i0).ravel(), (px - j0).ravel()])
        sx = ndimage.map_coordinates(gx, coords, order=1, mode="constant", cval=0.0).reshape(px.shape)
        sy = ndimage.map_coordinates(gy, coords, order=1, mode="constant", cval=0.0).reshape(px.shape)
        edge = sx * nx + sy * ny
        if self.occluder is None:
            return edge.mean(axis=1) / self.s_ref
        # a sphere against the robot: only the arc in view is scored; a pose hidden to less than a fifth scores 0
        seen = ~self.occluder(px, py)
        if seen.all():
            return edge.mean(axis=1) / self.s_ref
        n_seen = seen.sum(axis=1)
        score = (edge * seen).sum(axis=1) / np.maximum(n_seen, 1) / self.s_ref
        return np.where(n_seen >= MIN_SEEN * px.shape[1], score, 0.0)

    def _turn_check(self, image, new, score):
        """Score the estimate ``new`` as it is and half-turned, slid along its axis by up to half the outline's
        reach; if one of those poses scores higher than ``new``, move ``new`` and the whole cloud there. Returns the
        estimate's score.

        The outline is symmetric under a half turn but for its notches: a cloud that settled on a turned pose (one
        that matched the part of the robot in view as it entered the frame) sits in a local maximum of the score
        that particle diffusion does not leave; and a robot that moved along its axis further than the particles
        spread (frames without an image) is better matched by the estimate slid than by the estimate turned."""
        c, s = np.cos(new[2]), np.sin(new[2])
        slide = np.arange(-np.floor(self.reach / 2), np.floor(self.reach / 2) + 1, 2.0)
        turns = np.repeat([0.0, np.pi], slide.size)
        along = np.tile(slide, 2)
        poses = np.stack([new[0] + along * c, new[1] + along * s, new[2] + turns], axis=1)
        scores = self.scores(image, poses)
        k = int(np.argmax(scores))
        if scores[k] <= score:
            return score
        self.particles[:, 0] += poses[k, 0] - new[0]
        self.particles[:, 1] += poses[k, 1] - new[1]
        self.particles[:, 2] += turns[k]
        new[:2] = poses[k, :2]
        new[2] = np.arctan2(np.sin(poses[k, 2]), np.cos(poses[k, 2]))
        return float(scores[k])

    def step(self, image, valid, threshold):
        """Predict, weight on ``image`` (if valid), estimate, resample; returns the estimate's score."""
        spread = min(1.0 + self.searched, 10.0)
        self.particles[:, :2] += self.velocity + spread * self.sigma_px * self.rng.standard_normal((self.n, 2))
        if self.oriented:
            self.particles[:, 2] += spread * self.sigma_heading * self.rng.standard_normal(self.n)
        if not valid:
            self.estimate[:2] += self.velocity
            self.missed += 1
            return 0.0
        s = self.scores(image, self.particles)
        w = np.exp((s - s.max()) / self.tau)
        w /= w.sum()
        self.weights = w
        new = np.empty(3)
        new[:2] = w @ self.particles[:, :2]
        new[2] = np.arctan2(w @ np.sin(self.particles[:, 2]), w @ np.cos(self.particles[:, 2]))
        score = float(self.scores(image, new[None])[0])
        if self.oriented:
            score = self._turn_check(image, new, score)
        if score >= threshold:
            self.velocity = 0.5 * self.velocity + 0.5 * (new[:2] - self.estimate[:2]) if self.missed == 0 \
                else np.zeros(2)
            self.estimate = new
            self.missed = self.searched = 0
        else:
            self.missed += 1
            self.searched += 1
            self.velocity = np.zeros(2)
        if 1.0 / np.sum(w * w) < self.n / 2:
            idx = systematic_resample(w, self.rng)
            self.particles = self.particles[idx]
            self.weights = np.full(self.n, 1.0 / self.n)
        return score


class ImageTracker:
    """Particle filters for the robot (x, y, θ) and N spheres (x, y) on rendered or camera frames.

    Parameters
    ----------
    params : Params
        Parsed ``models/camera.toml`` (tables ``render`` and ``tracker``).
    n_spheres : int
    pixel : float
        Pixel size (m); pixel (i, j) is centred at (j·s, i·s).
    init_robot, init_heading, init_spheres : optional
        Prior positions (m) and heading; without them the first valid frame is searched.
    seed : int or numpy.random.Generator
        Seed of the particles' random stream, or the stream itself (the tracker block
        passes each trial's own generator).
    """

    def __init__(self, params: Params, *, n_spheres: int, pixel: float, dt: float, init_robot=None,
                 init_heading: float = 0.0, init_spheres=None, seed=0, shapes: SeenShapes | None = None):
        r, tr = params.render, params.tracker
        self.render, self.pixel, self.n_spheres, self.dt = r, float(pixel), int(n_spheres), float(dt)
        self.shapes = seen_shapes() if shapes is None else shapes
        self.outline_px = self.shapes.robot.scaled(1.0 / self.pixel)
        self.threshold = float(tr.edge_threshold)
        rng = np.random.default_rng(seed)
        n = int(tr.particles)
        sig, sig_h = float(tr.particle_position_sigma), float(tr.particle_heading_sigma)
        rpts, rnrm = robot_contour(self.outline_px, 3.0)
        spts, snrm = sphere_contour(self.shapes.sphere_radius / pixel)
        tau = 0.04
        self.robot = _ObjectFilter(rpts, rnrm, True, n, sig, sig_h, tau, rng)
        self.spheres = [_ObjectFilter(spts, snrm, False, n, sig, 0.0, tau, rng) for _ in range(self.n_spheres)]
        self._calibrate()
        self.started = False
        if init_robot is not None:
            sph = np.zeros((0, 2)) if init_spheres is None else np.asarray(init_spheres, dtype=float).reshape(-1, 2)
            if len(sph) != self.n_spheres:
                raise DetectionError(f"init_spheres has {len(sph)} rows, the tracker follows {self.n_spheres} spheres")
            self._start(np.asarray(init_robot, dtype=float) / pixel, float(init_heading), sph / pixel)

    def _calibrate(self):
        """Reference edge scores: each model scored at its true pose on a clean rendered frame."""
        r, s, robot = self.render, self.pixel, self.shapes.robot
        size = int(2 * (max(robot.length, robot.width) + 4 * self.shapes.sphere_radius) / s) + 20
        clean = render_frame(np.array([size / 2 * s, size / 2 * s]), 0.0, np.array([[size / 2 * s, 0.2 * size * s]]),
                             r, pixel=s, width=size, height=size, shapes=self.shapes)
        self.robot.s_ref = float(self.robot.scores(clean, np.array([[size / 2, size / 2, 0.0]]))[0])
        ref = float(self.spheres[0].scores(clean, np.array([[size / 2, 0.2 * size, 0.0]]))[0]) if self.spheres \
            else 1.0
        for f in self.spheres:
            f.s_ref = ref

    def _start(self, robot_px, heading, spheres_px):
        self.robot.reset(robot_px[0], robot_px[1], heading)
        for f, p in zip(self.spheres, spheres_px, strict=True):
            f.reset(p[0], p[1], 0.0)
        self.started = True

    def _robot_blob(self, image):
        """The robot's blob (the largest robot-dark one, at least a quarter of the robot's area) and the best-scoring
        pose near it, or ``(None, reason)``.

        The blob's major axis turned back by the outline's own (:attr:`RobotOutline.major_axis`) is the heading's
        line; both senses and offsets of up to 6 px from the blob's centroid are scored (the notches move the
        centroid off the body's origin, and a robot partly out of view has its blob cut by the frame)."""
        r = self.render
        very_dark = image < 0.5 * (r.sphere_level + r.robot_level)
        lab, n = ndimage.label(very_dark)
        if n == 0:
            return None, "no robot-dark blob"
        sizes = ndimage.sum_labels(very_dark, lab, np.arange(1, n + 1))
        robot_area = self.shapes.robot.area / self.pixel**2
        if sizes.max() < 0.25 * robot_area:  # a speck has no axis (its covariance is NaN): it is not the robot
            return None, (f"the largest robot-dark blob has {int(sizes.max())} pixels, under a quarter of the "
                          f"robot's {robot_area:.0f}")
        blob = lab == 1 + int(np.argmax(sizes))
        ii, jj = np.nonzero(blob)
        cx, cy, axis = principal_axis(np.ones(ii.size), jj, ii)
        theta = axis - self.shapes.robot.major_axis   # the blob's major axis → the heading
        cands = np.array([[cx + dx, cy + dy, th] for th in (theta, theta + np.pi) for dx in np.arange(-6, 7, 2)
                          for dy in np.arange(-6, 7, 2)])
        scores = self.robot.scores(image, cands)
        k = int(np.argmax(scores))
        return blob, (cands[k], float(scores[k]))

    def detect(self, image) -> None:
        """Initialise from dark blobs: the darkest large blob is the robot, sphere-sized blobs are spheres."""
        r = self.render
        dark = image < 0.5 * (r.background + r.sphere_level)
        blob, found_robot = self._robot_blob(image)
        if blob is None:
            raise DetectionError(f"{found_robot} in the first frame")
        best = found_robot[0]
        grown = ndimage.binary_dilation(blob, iterations=3)
        slab, sn = ndimage.label(dark & ~grown)
        area = np.pi * (self.shapes.sphere_radius / self.pixel) ** 2
        found = []
        if sn:
            sizes = ndimage.sum_labels(dark, slab, np.arange(1, sn + 1))
            centres = ndimage.center_of_mass(dark, slab, np.arange(1, sn + 1))
            found = [(c[1], c[0]) for c, a in zip(centres, sizes, strict=True) if 0.5 * area < a < 1.6 * area]
        if len(found) != self.n_spheres:
            raise DetectionError(f"found {len(found)} sphere-sized blobs, the tracker follows {self.n_spheres}")
        found.sort()
        self._start(best[:2], float(best[2]), np.asarray(found).reshape(-1, 2))

    def _reacquire(self, image) -> bool:
        """The particles missed the robot in this frame (it turned or moved further than they spread, or came back
        into view somewhere else): where a robot-dark blob shows a pose that scores at least the detection
        threshold, the cloud starts again there, as at detection, and the robot counts as found in this frame."""
        blob, found = self._robot_blob(image)
        if blob is None or found[1] < self.threshold:
            return False
        pose = found[0]
        self.robot.reset(pose[0], pose[1], pose[2])
        self.robot.velocity = np.zeros(2)
        self.robot.missed = self.robot.searched = 0
        return True

    def _robot_occluder(self):
        """Which pixel points the robot (at this frame's estimate) hides: inside its outline or on its blurred edge.
        A sphere pushed into the robot's notch is half hidden; its visible arc is what its filter scores."""
        x, y, heading = self.robot.estimate
        centre, outline = np.array([x, y]), self.outline_px
        return lambda px, py: robot_sdf(px, py, centre, heading, outline) < OCCLUSION_MARGIN_PX

    def step(self, image: np.ndarray, valid: bool):
        """Track one frame: the robot first, then the spheres with the part the robot hides left out. Returns
        ``(position m, heading, velocity m/s, spheres m, all found)``."""
        if not self.started:
            if not valid:
                return np.zeros(2), 0.0, np.zeros(2), np.zeros((self.n_spheres, 2)), False
            self.detect(image)
        found = bool(valid and self.robot.step(image, valid, self.threshold) >= self.threshold)
        if valid and not found:
            found = self._reacquire(image)
        occluder = self._robot_occluder()
        for f in self.spheres:
            f.occluder = occluder
            found &= bool(valid and f.step(image, valid, self.threshold) >= self.threshold)
        s = self.pixel
        pos = self.robot.estimate[:2] * s
        vel = self.robot.velocity * s / self.dt
        sph = np.array([f.estimate[:2] * s for f in self.spheres]).reshape(-1, 2)
        return pos, float(self.robot.estimate[2]), vel, sph, found
