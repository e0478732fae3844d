"""A :class:`~magctl.rig.devices.base.Camera` on OpenCV's ``cv2.VideoCapture``: USB/V4L2 cameras, GStreamer
pipelines and video files (replay of a recorded run).

**Sources.** ``source`` is

* an ``int`` (or a string of digits) — a camera index (``cv2.CAP_ANY`` picks the backend; V4L2 on Linux);
* ``"/dev/videoN"`` — a V4L2 device node (``cv2.CAP_V4L2``);
* a string with ``!`` in it — a GStreamer pipeline ending in ``appsink`` (``cv2.CAP_GSTREAMER``; the pip wheels
  of OpenCV are built without GStreamer, a distribution's or a self-built OpenCV has it);
* a URL (``rtsp://…``, ``http://…``, ``udp://…``) — a network stream (``cv2.CAP_ANY``: FFmpeg), read live;
* anything else — a video file (``str`` or :class:`os.PathLike`).

``api`` overrides the backend (a ``cv2.CAP_*`` constant).

**Frame numbers** come from the device, never from the host's clock (a gap is a dropped frame,
:func:`~magctl.rig.devices.base.dropped_between`):

* files: the decoder's position ``CAP_PROP_POS_FRAMES`` (0 for the first frame); a file holds no gaps, unless
  ``numbers`` gives the device number of each frame in the file (a recording's sidecar: the frames the
  recorder missed then show as gaps, as they did live);
* live sources whose backend stamps its buffers (``CAP_PROP_POS_MSEC`` > 0 on the first frame: V4L2 drivers
  stamp each buffer at capture, GStreamer gives the buffer's running time): each frame's number is the
  previous one plus the timestamp step divided by the nominal ``period``, rounded (at least 1) — a step
  rather than an absolute quotient, so a rate a little off nominal does not accumulate into false gaps; a frame
  whose stamp does not advance counts as the next frame, one nominal period on;
* other live sources: a counter of the frames the reader received; drops inside the driver are then
  invisible, only those of this adapter's own buffer (a consumer slower than the camera) show.

:attr:`OpenCVCamera.numbering` says which (``"file"``, ``"sidecar"``, ``"timestamp"`` or ``"counter"``).

**Timestamps**: the capture's timestamp ``CAP_PROP_POS_MSEC`` (files: the frame's presentation time; with
``numbers``: ``number · period``), else ``time.monotonic()`` when the reader grabbed the frame.

**Grabbing.** A live source is read by a thread of its own into a small buffer (``buffer`` frames; when the
consumer falls behind the oldest frame is discarded, which shows as a gap in the numbers), so that
:meth:`OpenCVCamera.grab` returns ``None`` after ``timeout`` s even when the device hangs inside
``VideoCapture.read``. A live source whose read fails (unplugged, pipeline ended) raises
:class:`~magctl.rig.devices.base.DeviceError` from the next grab that finds the buffer empty. Files are read
synchronously; at their end ``grab`` returns ``None`` and :attr:`OpenCVCamera.ended` is set. (Opening is not
guarded: ``cv2.VideoCapture`` itself may take the backend's own time to give up on a device that does not answer;
OpenCV's V4L2 backend gives up on a silent device after its select timeout, 10 s, which ends the reader.) With
``realtime=True`` a file's frames are paced at their timestamps (a replay at the recorded rate), else they come
as fast as they decode.

Frames are converted with :func:`~magctl.rig.devices.base.to_gray`. OpenCV (``opencv-python-headless``) is an
optional dependency, imported by :meth:`OpenCVCamera.open`.
"""

from __future__ import annotations

import collections
import math
import os
import threading
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from magctl import FRAME_PERIOD_S
from magctl.rig.devices.base import Camera, DeviceError, Frame, to_gray


class _Stopped:
    """The reader thread's last item in its buffer: it has stopped (why) and released the capture."""

    def __init__(self, why: str):
        self.why = why


class OpenCVCamera(Camera):
    """A camera, GStreamer pipeline or video file read through ``cv2.VideoCapture`` (see the module docstring).

    Parameters
    ----------
    source : int, str or os.PathLike
        Camera index, ``/dev/videoN``, GStreamer pipeline (contains ``!``), stream URL or video file.
    name : str
        The device's name in error messages.
    period : float, optional
        Nominal frame period, s: divides timestamp steps into frame numbers. Default: the source's
        ``CAP_PROP_FPS``, else 1/30 s.
    realtime : bool
        Files only: pace frames at their timestamps instead of as fast as they decode.
    numbers : sequence of int, optional
        Files only: the device frame number of each frame in the file (increasing), e.g. a recording's
        sidecar, so that the frames lost while recording count as dropped.
    api : int, optional
        A ``cv2.CAP_*`` backend instead of the one chosen from the source.
    buffer : int
        Live sources: frames held for the consumer (oldest discarded first).
    open_timeout : float
        Live sources: seconds :meth:`open` waits for a first frame when the backend does not report the size.
    """

    def __init__(self, source: int | str | os.PathLike, *, name: str = "camera", period: float | None = None,
                 realtime: bool = False, numbers: Sequence[int] | None = None, api: int | None = None,
                 buffer: int = 4, open_timeout: float = 5.0):
        if isinstance(source, str) and source.strip().isdigit():
            source = int(source)  # "0" from a command line or a config file is the camera index
        self.source = source
        self.name = str(name)
        self.kind = _kind(source)
        self._period = None if period is None else float(period)
        if self._period is not None and not (math.isfinite(self._period) and self._period > 0):
            raise ValueError(f"{self.name}: period must be > 0 s, got {period!r}")
        self.period = self._period if self._period is not None else FRAME_PERIOD_S
        self.realtime = bool(realtime)
        self.numbers = None
        if numbers is not None:
            if self.kind != "file":
                raise ValueError(f"{self.name}: numbers apply to video files, not to {self.describe()}")
            nums = np.asarray(numbers)
            if nums.ndim != 1 or nums.size == 0 or nums.dtype.kind not in "iu" or np.any(np.diff(nums) <= 0):
                raise ValueError(f"{self.name}: numbers must be a non-empty increasing sequence of integers")
            self.numbers = [int(n) for n in nums]
        self.api = api
        self.buffer = max(1, int(buffer))
        self.open_timeout = float(open_timeout)
        self.ended = False
        """A file has been read to its end (:meth:`grab` returns None from then on)."""
        self.numbering = "sidecar" if self.numbers is not None else ("file" if self.kind == "file" else None)
        """How frame numbers are made: ``"file"``, ``"sidecar"``, ``"timestamp"`` or ``"counter"`` (live sources:
        known after the first frame)."""
        self._cv2 = None
        self._cap = None
        self._shape: tuple[int, int] | None = None
        self._open = False
        self._closed = False
        # files
        self._index = 0
        self._last_t = -math.inf
        self._pending: Frame | None = None
        self._pace0: tuple[float, float] | None = None  # (wall clock, file time) of the first paced frame
        # live sources
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._cond = threading.Condition()
        self._queue: collections.deque = collections.deque()
        self.discarded = 0
        """Live sources: frames discarded because the consumer fell behind (they show as gaps)."""

    # --- Camera ----------------------------------------------------------------------------------------------
    def describe(self) -> str:
        """The source in words, for messages (``video file x.avi``, ``device 0``, ``GStreamer pipeline '…'``)."""
        if self.kind == "file":
            return f"video file {os.fspath(self.source)}"
        if self.kind == "gstreamer":
            return f"GStreamer pipeline {self.source!r}"
        if self.kind == "stream":
            return f"stream {self.source}"
        return f"device {self.source}"

    def open(self) -> None:
        """Open the source; raise :class:`DeviceError` naming the camera and the source when it cannot be."""
        if self._open:
            return
        try:
            import cv2
        except ImportError:
            raise DeviceError(self.name, f"cannot open {self.describe()}: OpenCV is not installed "
                                         "(pip install opencv-python-headless)") from None
        self._cv2 = cv2
        if self.kind == "file" and not Path(self.source).is_file():
            raise DeviceError(self.name, f"cannot open {self.describe()}: no such file")
        api = self.api if self.api is not None else {"file": cv2.CAP_ANY, "index": cv2.CAP_ANY, "stream": cv2.CAP_ANY,
                                                     "node": cv2.CAP_V4L2, "gstreamer": cv2.CAP_GSTREAMER}[self.kind]
        if self.kind == "gstreamer" and self.api is None and not cv2.videoio_registry.hasBackend(cv2.CAP_GSTREAMER):
            raise DeviceError(self.name, f"cannot open {self.describe()}: this OpenCV build "
                                         f"({cv2.__version__}) has no GStreamer backend")
        src = os.fspath(self.source) if self.kind == "file" else self.source
        try:
            cap = cv2.VideoCapture(src, api)
        except cv2.error as err:
            msg = " ".join(str(err).split())
            raise DeviceError(self.name, f"cannot open {self.describe()}: {msg}") from None
        if not cap.isOpened():
            cap.release()
            why = {"file": "OpenCV cannot decode it", "gstreamer": "the pipeline does not start",
                   "stream": "the stream does not answer or cannot be decoded",
                   "index": "no camera there, or it is busy", "node": "no camera there, or it is busy"}[self.kind]
            raise DeviceError(self.name, f"cannot open {self.describe()}: {why}")
        fps = cap.get(cv2.CAP_PROP_FPS)
        if self._period is None and math.isfinite(fps) and fps > 0:
            self.period = 1.0 / fps
        w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        self._shape = (h, w) if h > 0 and w > 0 else None
        self._cap = cap
        self._closed = False
        self.ended = False
        self._index, self._last_t, self._pending, self._pace0 = 0, -math.inf, None, None
        self.discarded = 0
        if self.kind != "file":
            self.numbering = None
            # a fresh buffer and stop flag per opening: a reader of an earlier one, stuck in its driver, never
            # delivers into this one
            self._queue, self._stop = collections.deque(), threading.Event()
            self._thread = threading.Thread(target=self._reader, args=(cap, self._queue, self._stop),
                                            name=f"{self.name} reader", daemon=True)
            self._thread.start()
        self._open = True
        if self._shape is None:
            self._learn_shape()

    def grab(self, timeout: float) -> Frame | None:
        """The next frame, or None: nothing came within ``timeout`` s (live), or the file has ended
        (:attr:`ended`). Raises :class:`DeviceError` when not open or when a live source has failed."""
        if not self._open:
            state = "closed" if self._closed else "not open"
            raise DeviceError(self.name, f"{self.describe()} is {state}")
        if self.kind == "file":
            return self._grab_file(float(timeout))
        return self._grab_live(float(timeout))

    def close(self) -> None:
        """Release the source (idempotent). A live reader stuck inside the driver is left to release the capture
        when (if) its read returns."""
        if self._open:
            self._open = False
            self._closed = True
            if self._thread is not None:
                self._stop.set()
                self._thread.join(timeout=1.0)
                self._thread = None
            elif self._cap is not None:
                self._cap.release()
            self._cap = None
        self._closed = True

    @property
    def shape(self) -> tuple[int, int]:
        if self._shape is None:
            raise DeviceError(self.name, f"{self.describe()} is not open: its frame size is not known")
        return self._shape

    # --- files -----------------------------------------------------------------------------------------------
    def _read_file(self) -> Frame | None:
        cv2, cap = self._cv2, self._cap
        ok, img = cap.read()
        if not ok or img is None:
            self.ended = True
            return None
        index = int(round(cap.get(cv2.CAP_PROP_POS_FRAMES))) - 1
        if index < self._index:  # a backend that does not report its position
            index = self._index
        self._index = index + 1
        if self.numbers is not None:
            if index >= len(self.numbers):
                raise DeviceError(self.name, f"{self.describe()} has more frames than the {len(self.numbers)} "
                                             "numbers given for it")
            number = self.numbers[index]
            t = number * self.period
        else:
            number = index
            t = cap.get(cv2.CAP_PROP_POS_MSEC) / 1000.0
            if not (math.isfinite(t) and t > self._last_t):
                t = index * self.period if index * self.period > self._last_t else self._last_t + self.period
        self._last_t = t
        return Frame(to_gray(img), t, number)

    def _grab_file(self, timeout: float) -> Frame | None:
        if self.ended:
            return None
        frame = self._pending if self._pending is not None else self._read_file()
        self._pending = None
        if frame is None or not self.realtime:
            return frame
        now = time.monotonic()
        if self._pace0 is None:
            self._pace0 = (now, frame.t)
        due = self._pace0[0] + (frame.t - self._pace0[1])
        if due - now > timeout:
            time.sleep(max(timeout, 0.0))
            self._pending = frame
            return None
        if due > now:
            time.sleep(due - now)
        return frame

    def _learn_shape(self) -> None:
        """The frame size from a first frame, for backends that do not report it."""
        if self.kind == "file":
            self._pending = self._read_file()
            if self._pending is None:
                self.close()
                raise DeviceError(self.name, f"cannot open {self.describe()}: it holds no frames")
            self._shape = self._pending.image.shape
            return
        with self._cond:
            self._cond.wait_for(lambda: self._queue, timeout=self.open_timeout)
            first = self._queue[0] if self._queue else None
        if not isinstance(first, Frame):
            self.close()
            why = first.why if first is not None else f"no frame within {self.open_timeout:g} s"
            raise DeviceError(self.name, f"cannot open {self.describe()}: {why}")
        self._shape = first.image.shape

    # --- live sources ----------------------------------------------------------------------------------------
    def _reader(self, cap, queue: collections.deque, stop: threading.Event) -> None:
        """Reader thread: grab, stamp, number, buffer; releases the capture when it stops."""
        cv2 = self._cv2
        number, last_ms, t = -1, None, -math.inf
        why = "closed"
        try:
            while not stop.is_set():
                if not cap.grab():
                    why = "the source stopped delivering frames (read failed)"
                    break
                t_host = time.monotonic()
                ok, img = cap.retrieve()
                if not ok or img is None:
                    why = "the source delivered a frame that could not be decoded"
                    break
                if stop.is_set():
                    break
                ms = cap.get(cv2.CAP_PROP_POS_MSEC)
                stamped = math.isfinite(ms) and ms > 0
                if self.numbering is None:
                    self.numbering = "timestamp" if stamped else "counter"
                if self.numbering == "counter":
                    number, t = number + 1, t_host
                elif stamped and (last_ms is None or ms > last_ms):
                    step = 1 if last_ms is None else max(1, round((ms - last_ms) / 1000.0 / self.period))
                    number, last_ms, t = number + step, ms, ms / 1000.0
                else:  # a stamp that does not advance: taken as the next frame, one nominal period on
                    number, t = number + 1, t + self.period
                    last_ms = t * 1000.0
                frame = Frame(to_gray(img), t, number)
                with self._cond:
                    if len(queue) >= self.buffer:
                        queue.popleft()
                        self.discarded += 1
                    queue.append(frame)
                    self._cond.notify_all()
        except Exception as err:  # noqa: BLE001 — a driver error ends the reader; grab() reports it
            why = f"the reader failed: {type(err).__name__}: {' '.join(str(err).split())}"
        finally:
            cap.release()
            with self._cond:
                queue.append(_Stopped(why))
                self._cond.notify_all()

    def _grab_live(self, timeout: float) -> Frame | None:
        with self._cond:
            self._cond.wait_for(lambda: self._queue, timeout=max(timeout, 0.0))
            if not self._queue:
                return None
            item = self._queue[0]
            if isinstance(item, _Stopped):  # left in place: every later grab raises too
                raise DeviceError(self.name, f"{self.describe()}: {item.why}")
            return self._queue.popleft()


def _kind(source) -> str:
    if isinstance(source, bool):
        raise TypeError(f"camera source must be an index, a device path, a pipeline or a file, not {source!r}")
    if isinstance(source, (int, np.integer)):
        return "index"
    if isinstance(source, str) and "!" in source:
        return "gstreamer"
    if isinstance(source, str) and "://" in source:
        return "stream"
    if isinstance(source, (str, os.PathLike)):
        return "node" if os.fspath(source).startswith("/dev/video") else "file"
    raise TypeError(f"camera source must be an index, a device path, a pipeline or a file, not {source!r}")
