"""OpenCVCamera: the camera contract on a video file written with write_video, one-line errors naming the camera and
the source, the end of a file, a recording's frame numbers, and the live-source path (reader thread, numbers from
the capture's timestamps or a counter, a hung or failed device) on a stand-in for ``cv2.VideoCapture``."""

from __future__ import annotations

import threading

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")

from magctl.rig.devices.base import DeviceError, dropped_between  # noqa: E402
from magctl.rig.devices.contract import check_camera  # noqa: E402
from magctl.rig.devices.opencv_camera import OpenCVCamera  # noqa: E402
from magctl.rig.devices.video import to_levels, write_video  # noqa: E402


def _frames(n, h=48, w=64, seed=0):
    rng = np.random.default_rng(seed)
    return [rng.random((h, w)) for _ in range(n)]


@pytest.fixture
def clip(tmp_path):
    path = tmp_path / "clip.avi"
    frames = _frames(8)
    write_video(path, frames, 30.0, "FFV1")
    return path, frames


def test_contract_on_a_video_file(clip):
    path, _ = clip
    check_camera(lambda: OpenCVCamera(path, name="replay"), frames=6)


def test_file_frames_numbers_and_timestamps(clip):
    path, frames = clip
    with OpenCVCamera(path) as cam:
        assert cam.shape == (48, 64) and cam.period == pytest.approx(1 / 30)
        got = [cam.grab(1.0) for _ in range(len(frames))]
    assert [f.number for f in got] == list(range(len(frames)))
    assert [f.t for f in got] == pytest.approx([k / 30 for k in range(len(frames))])
    for f, ref in zip(got, frames, strict=True):  # lossless: the 8-bit levels written come back
        np.testing.assert_array_equal(np.round(f.image * 255).astype(np.uint8), to_levels(ref))
        assert f.image.dtype == np.float64


def test_end_of_file_returns_none_and_sets_ended(clip):
    path, frames = clip
    with OpenCVCamera(path) as cam:
        for _ in frames:
            assert cam.grab(1.0) is not None
        assert not cam.ended
        assert cam.grab(1.0) is None and cam.ended
        assert cam.grab(1.0) is None


def test_realtime_replay_delivers_every_frame_in_order(tmp_path):
    path = tmp_path / "fast.avi"
    write_video(path, _frames(5), 200.0, "MJPG")
    with OpenCVCamera(path, realtime=True) as cam:
        numbers = [cam.grab(2.0).number for _ in range(5)]
        assert cam.grab(2.0) is None and cam.ended
    assert numbers == [0, 1, 2, 3, 4]


def test_a_recordings_frame_numbers_show_its_drops(clip):
    path, frames = clip
    numbers = [10, 11, 12, 16, 17, 18, 25, 26]
    with OpenCVCamera(path, numbers=numbers, period=0.05) as cam:
        got = [cam.grab(1.0) for _ in frames]
        assert cam.numbering == "sidecar"
    assert [f.number for f in got] == numbers
    assert [f.t for f in got] == pytest.approx([n * 0.05 for n in numbers])
    assert sum(dropped_between(a.number, b.number) for a, b in zip(got, got[1:])) == 3 + 6


def test_sidecar_shorter_than_the_file_is_an_error(clip):
    path, _ = clip
    with OpenCVCamera(path, numbers=[0, 1]) as cam:
        cam.grab(1.0), cam.grab(1.0)
        with pytest.raises(DeviceError, match="more frames than the 2 numbers"):
            cam.grab(1.0)


@pytest.mark.parametrize("source, words", [
    ("missing.avi", ["replay", "video file", "missing.avi", "no such file"]),
    (99, ["replay", "device 99"]),
    ("99", ["replay", "device 99"]),  # a string of digits from a config file is an index
    ("/dev/video99", ["replay", "device /dev/video99"]),
    ("nosuchelement ! appsink", ["replay", "GStreamer pipeline 'nosuchelement ! appsink'"]),
])
def test_unopenable_source_is_one_line_naming_camera_and_source(tmp_path, monkeypatch, source, words):
    monkeypatch.chdir(tmp_path)
    cam = OpenCVCamera(source, name="replay")
    with pytest.raises(DeviceError) as err:
        cam.open()
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith("replay: ")
    for w in words:
        assert w in msg
    with pytest.raises(DeviceError, match="not open"):
        cam.grab(0.1)


def test_a_file_that_is_not_a_video(tmp_path):
    bad = tmp_path / "notes.avi"
    bad.write_text("not a video")
    with pytest.raises(DeviceError, match=r"^camera: cannot open video file .*notes\.avi"):
        OpenCVCamera(bad).open()


def test_bad_options():
    with pytest.raises(ValueError, match="period"):
        OpenCVCamera("x.avi", period=0.0)
    with pytest.raises(ValueError, match="increasing"):
        OpenCVCamera("x.avi", numbers=[3, 2])
    with pytest.raises(ValueError, match="video files"):
        OpenCVCamera(0, numbers=[0, 1])
    with pytest.raises(TypeError):
        OpenCVCamera(1.5)


def test_write_video_codec_that_will_not_open(tmp_path):
    for codec, where in (("ZZZZ", tmp_path / "a.avi"), ("FFV1", tmp_path / "no" / "dir" / "a.avi")):
        with pytest.raises(DeviceError) as err:
            write_video(where, _frames(2), 30.0, codec)
        msg = str(err.value)
        assert "\n" not in msg and codec in msg and str(where) in msg
    with pytest.raises(DeviceError, match="four-character"):
        write_video(tmp_path / "b.avi", _frames(2), 30.0, "FFV")


def test_write_video_refuses_bad_frames(tmp_path):
    with pytest.raises(ValueError, match="frame 1 has shape"):
        write_video(tmp_path / "a.avi", [np.zeros((4, 6)), np.zeros((4, 5))], 30.0)
    with pytest.raises(ValueError, match="not finite"):
        write_video(tmp_path / "b.avi", [np.full((4, 6), np.nan)], 30.0)
    with pytest.raises(ValueError, match="no frames"):
        write_video(tmp_path / "c.avi", [], 30.0)


# --- live sources, on a stand-in for cv2.VideoCapture ------------------------------------------------------------
class FakeCapture:
    """A live capture: frames with optional buffer stamps (ms); it can hang (block until released) or fail."""

    def __init__(self, n, stamps_ms=None, hang_after=None, fail_after=None, fps=30.0):
        self.n, self.stamps, self.hang_after, self.fail_after, self.fps = n, stamps_ms, hang_after, fail_after, fps
        self.k = -1
        self.released = threading.Event()

    def isOpened(self):  # noqa: N802 - OpenCV's name
        return True

    def get(self, prop):
        if prop == cv2.CAP_PROP_FPS:
            return self.fps
        if prop == cv2.CAP_PROP_FRAME_WIDTH:
            return 8
        if prop == cv2.CAP_PROP_FRAME_HEIGHT:
            return 6
        if prop == cv2.CAP_PROP_POS_MSEC:
            return 0.0 if self.stamps is None else float(self.stamps[self.k])
        return 0.0

    def grab(self):
        if self.hang_after is not None and self.k + 1 >= self.hang_after:
            self.released.wait()
            return False
        if (self.fail_after is not None and self.k + 1 >= self.fail_after) or self.k + 1 >= self.n:
            return False
        self.k += 1
        return True

    def retrieve(self):
        return True, np.full((6, 8, 3), (10 * self.k) % 256, np.uint8)

    def release(self):
        self.released.set()


@pytest.fixture
def fake(monkeypatch):
    made = {}

    def install(**kw):
        cap = FakeCapture(**kw)
        monkeypatch.setattr(cv2, "VideoCapture", lambda *a, **k: cap)
        made["cap"] = cap
        return cap

    return install


def test_live_numbers_from_buffer_stamps_show_drops(fake):
    # 30 frames/s stamped by the driver; two frames missing after the third, a little jitter throughout
    fake(n=6, stamps_ms=[1000.0, 1033.0, 1067.5, 1166.0, 1200.2, 1233.0])
    with OpenCVCamera(0, name="usb", buffer=16) as cam:
        got = [cam.grab(2.0) for _ in range(6)]
        assert cam.numbering == "timestamp"
    assert [f.number for f in got] == [0, 1, 2, 5, 6, 7]
    assert [f.t for f in got] == pytest.approx([1.0, 1.033, 1.0675, 1.166, 1.2002, 1.233])
    assert got[2].image[0, 0] == pytest.approx(20 / 255)


def test_live_numbers_from_a_counter_when_the_backend_does_not_stamp(fake):
    fake(n=4)
    with OpenCVCamera(0, buffer=16) as cam:
        got = [cam.grab(2.0) for _ in range(4)]
        assert cam.numbering == "counter"
    assert [f.number for f in got] == [0, 1, 2, 3]
    assert all(b.t >= a.t for a, b in zip(got, got[1:]))


def _settle(condition, timeout=5.0):
    """Wait (polling) until the reader thread has done what ``condition`` checks; synchronisation, not timing."""
    done = threading.Event()
    for _ in range(int(timeout / 0.01)):
        if condition():
            return
        done.wait(0.01)
    raise AssertionError("the reader thread did not get there")


def test_live_consumer_falling_behind_sees_the_discarded_frames_as_a_gap(fake):
    cap = fake(n=10, hang_after=10)
    with OpenCVCamera(0, buffer=3) as cam:
        _settle(lambda: cam.discarded == 7)
        got = [cam.grab(2.0) for _ in range(3)]
        cap.release()  # let the reader, stuck in the last grab, go
    assert [f.number for f in got] == [7, 8, 9]


def test_hung_device_returns_none_within_the_timeout(fake):
    cap = fake(n=100, hang_after=2)
    with OpenCVCamera(0) as cam:
        assert cam.grab(2.0).number == 0
        assert cam.grab(2.0).number == 1
        assert cam.grab(0.2) is None  # the reader is stuck inside the driver; grab is not
    cap.release()


def test_failed_device_raises_device_error(fake):
    fake(n=100, fail_after=1)
    with OpenCVCamera(0, name="usb") as cam:
        assert cam.grab(2.0).number == 0
        with pytest.raises(DeviceError, match=r"^usb: device 0: the source stopped delivering frames"):
            cam.grab(2.0)
        with pytest.raises(DeviceError):
            cam.grab(0.0)


def test_reopening_a_live_source_starts_afresh(fake):
    fake(n=3)
    cam = OpenCVCamera(0, buffer=8)
    with cam:
        assert [cam.grab(2.0).number for _ in range(3)] == [0, 1, 2]
    fake(n=2)
    with cam:
        assert [cam.grab(2.0).number for _ in range(2)] == [0, 1]
        with pytest.raises(DeviceError, match="stopped delivering"):
            cam.grab(2.0)


def test_contract_on_a_live_source(fake):
    fake(n=50, stamps_ms=[1000.0 + 33.3 * k for k in range(50)])
    check_camera(lambda: OpenCVCamera(0, name="usb", buffer=64))
