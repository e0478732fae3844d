"""Grayscale frames to a video file through OpenCV (``cv2.VideoWriter``).

Used by the tests of the camera adapter and the tracker, by the simulated hardware path and by labs that
record a run. Frames are grayscale floats in [0, 1] (the :class:`~magctl.rig.devices.base.Frame` convention);
they are written as 8-bit levels ``round(255 · v)``, so a file read back with
:class:`~magctl.rig.devices.opencv_camera.OpenCVCamera` gives every value to within 1/510 with a lossless
codec (``FFV1``) and to the codec's own error with a lossy one (``MJPG``).

OpenCV is an optional dependency (``opencv-python-headless``); it is imported when a video is written.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from magctl.rig.devices.base import DeviceError

WRITER = "video writer"
"""The device name in :class:`DeviceError` messages of :func:`write_video`."""


def _cv2():
    try:
        import cv2
    except ImportError:
        raise DeviceError(WRITER, "OpenCV is not installed (pip install opencv-python-headless)") from None
    return cv2


def to_levels(image: np.ndarray) -> np.ndarray:
    """A grayscale [0, 1] frame as 8-bit levels ``round(255 · clip(v, 0, 1))``."""
    return np.round(np.clip(np.asarray(image, dtype=float), 0.0, 1.0) * 255.0).astype(np.uint8)


def write_video(path: str | os.PathLike, frames: Iterable[np.ndarray], fps: float, codec: str = "FFV1") -> int:
    """Write grayscale float [0, 1] frames, all of one shape (H, W), to an 8-bit video at ``fps`` frames/s.

    ``codec`` is a four-character code (``FFV1``: lossless; ``MJPG``: lossy, widely readable); the container
    follows the file's extension (``.avi`` holds both). Values outside [0, 1] are clipped.

    Returns
    -------
    int
        The number of frames written.

    Raises
    ------
    DeviceError
        One line naming the codec and the path when the writer will not open (unknown code, a codec this
        OpenCV build lacks, a container that does not take it, a folder that does not exist).
    ValueError
        A frame that is not 2-D, differs in shape from the first, or has a pixel that is not finite.
    """
    cv2 = _cv2()
    path = Path(path)
    if not (isinstance(codec, str) and len(codec) == 4):
        raise DeviceError(WRITER, f"codec {codec!r} is not a four-character code (writing {path})")
    if not fps > 0:
        raise ValueError(f"{path}: fps must be > 0, got {fps!r}")
    writer = None
    shape = None
    count = 0
    try:
        for k, frame in enumerate(frames):
            img = np.asarray(frame, dtype=float)
            if img.ndim != 2:
                raise ValueError(f"{path}: frame {k} has shape {img.shape}, expected a 2-D grayscale image")
            if shape is None:
                shape = img.shape
                writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*codec), float(fps),
                                         (shape[1], shape[0]), False)
                if not writer.isOpened():
                    why = "" if path.parent.is_dir() else f" (folder {path.parent} does not exist)"
                    raise DeviceError(WRITER, f"codec {codec} will not open for {path}{why} "
                                              f"(OpenCV {cv2.__version__})")
            elif img.shape != shape:
                raise ValueError(f"{path}: frame {k} has shape {img.shape}, the first frame {shape}")
            if not np.all(np.isfinite(img)):
                raise ValueError(f"{path}: frame {k} has pixels that are not finite")
            writer.write(to_levels(img))
            count += 1
    finally:
        if writer is not None:
            writer.release()
    if shape is None:
        raise ValueError(f"{path}: no frames to write")
    return count
