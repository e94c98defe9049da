"""RigCamera against a fake cv2.VideoCapture (injected through open_capture): settings, crops, stale frames."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from psmini.errors import RigError
from psmini.rig.camera import CameraSettings, FrameCheck, RigCamera, centre_crop, to_gray


class FakeCapture:
    """What a webcam looks like to OpenCV: frames from a list (then the last one), properties that may not take."""

    def __init__(self, frames, opened=True, ignored=(), failures=0):
        self.frames, self.opened, self.ignored, self.failures = list(frames), opened, set(ignored), failures
        self.props = {cv2.CAP_PROP_FRAME_WIDTH: 640.0, cv2.CAP_PROP_FRAME_HEIGHT: 480.0}
        self.opened_with = None
        self.grabs = self.reads = 0
        self.released = False

    def isOpened(self):  # noqa: N802
        return self.opened

    def read(self):
        self.reads += 1
        if self.failures:
            self.failures -= 1
            return False, None
        frame = self.frames.pop(0) if len(self.frames) > 1 else self.frames[0]
        return True, frame.copy()

    def grab(self):
        self.grabs += 1
        return self.read()[0]

    def set(self, prop, value):
        if prop in self.ignored:
            return False
        if prop == cv2.CAP_PROP_EXPOSURE:
            value = round(value)  # a driver that rounds to its steps
        self.props[prop] = float(value)
        return True

    def get(self, prop):
        return self.props.get(prop, -1.0)

    def getBackendName(self):  # noqa: N802
        return "FAKE"

    def release(self):
        self.released = True


def opener(capture):
    def open_capture(source, backend):
        capture.opened_with = (source, backend)
        return capture
    return open_capture


def coded_frame(value=None):
    """A 640x480 BGR frame whose gray value encodes the column (so crops can be located)."""
    frame = np.zeros((480, 640, 3), np.uint8)
    frame[:] = (np.arange(640) % 256).astype(np.uint8)[None, :, None] if value is None else value
    return frame


def test_to_gray_weights_and_depths():
    bgr = np.zeros((1, 3, 3), np.uint8)
    bgr[0, 0, 2], bgr[0, 1, 1], bgr[0, 2, 0] = 255, 255, 255  # red, green, blue
    np.testing.assert_allclose(to_gray(bgr)[0], [0.2989, 0.5870, 0.1140], atol=1e-6)
    np.testing.assert_allclose(to_gray(np.full((2, 2), 65535, np.uint16)), 1.0)
    for bad in (np.zeros((2, 2), np.float32), np.zeros((2, 2, 4), np.uint8), np.zeros((0,), np.uint8), None):
        with pytest.raises(RigError):
            to_gray(bad)


def test_centre_crop_of_640x480():
    image = np.arange(480 * 640).reshape(480, 640)
    crop, box = centre_crop(image, 400)
    assert box == [120, 40, 400, 400]
    assert crop[0, 0] == image[40, 120] and crop.shape == (400, 400)
    with pytest.raises(RigError, match="smaller than the 500x500 crop"):
        centre_crop(image, 500)


def test_open_sets_reads_back_and_records_settings():
    capture = FakeCapture([coded_frame()], ignored={cv2.CAP_PROP_WB_TEMPERATURE})
    settings = CameraSettings(exposure=-5.4, gain=3.0, white_balance=4500.0)
    with RigCamera(2, backend="v4l2", settings=settings, open_capture=opener(capture)) as camera:
        report = camera.report
        assert capture.opened_with == (2, cv2.CAP_V4L2)
        assert report["requested"]["auto_exposure"] == 1.0  # V4L2's "manual"
        assert report["read_back"]["exposure"] == -5.0 and report["took"]["exposure"] is False
        assert report["took"]["gain"] is True and report["took"]["wb_temperature"] is False
        assert report["backend_name"] == "FAKE" and report["frame_size"] == [640, 480]
        image = camera.read()
        assert image.shape == (400, 400) and image.dtype == np.float32
        np.testing.assert_allclose(image[0, :3] * 255, np.array([120, 121, 122]) * 0.9999, atol=1e-3)
        assert camera.crop == [120, 40, 400, 400]
    assert capture.released


def test_dshow_manual_exposure_value():
    capture = FakeCapture([coded_frame()])
    with RigCamera(0, backend="dshow", settings=CameraSettings(exposure=-6), open_capture=opener(capture)) as camera:
        assert camera.report["requested"]["auto_exposure"] == 0.25


@pytest.mark.parametrize("settings, match", [
    ({"exposure": math.nan}, "exposure must be a finite number"),
    ({"gain": math.inf}, "gain must be a finite number"),
    ({"white_balance": "4500"}, "white_balance must be a finite number"),
    ({"buffer_size": 0}, "buffer_size must be an integer >= 1"),
])
def test_settings_that_cannot_be_recorded_are_refused_before_the_camera_opens(settings, match):
    """A NaN exposure was set on the camera and recorded, and the capture failed to write only after the whole
    acquisition (the manifest is strict JSON)."""
    with pytest.raises(RigError, match=match):
        CameraSettings(**settings)


def test_open_failures():
    with pytest.raises(RigError, match="cannot open camera 5"):
        RigCamera(5, backend="v4l2", open_capture=opener(FakeCapture([coded_frame()], opened=False))).open()
    small = FakeCapture([np.zeros((240, 320, 3), np.uint8)])
    with pytest.raises(RigError, match="delivers 320x240 frames"):
        RigCamera(0, backend="v4l2", open_capture=opener(small)).open()
    assert small.released
    with pytest.raises(RigError, match="unknown camera backend"):
        RigCamera(0, backend="firewire")
    with pytest.raises(RigError, match="crop_size"):
        RigCamera(0, crop_size=600)
    for bad in ("640x480", (640,), (640.0, 480), (0, 480), (True, 480)):  # a bare unpacking error before
        with pytest.raises(RigError, match=r"frame_size must be a \(width, height\) pair of positive integers"):
            RigCamera(0, frame_size=bad)  # type: ignore[arg-type]


def test_no_frame_after_retries():
    capture = FakeCapture([coded_frame()], failures=2)
    with RigCamera(0, backend="v4l2", read_retries=3, open_capture=opener(capture)) as camera:
        capture.failures = 4
        with pytest.raises(RigError, match="returned no frame in 4 reads"):
            camera.read()


def test_read_fresh_discards_buffered_and_stale_frames():
    stale, fresh = coded_frame(10), coded_frame(200)
    capture = FakeCapture([stale] * 7 + [fresh])
    with RigCamera(0, backend="v4l2", flush_frames=3, max_stale_frames=10, open_capture=opener(capture)) as camera:
        frame, _ = camera.read_fresh(lambda f: None if f.mean() > 0.5 else "dark", "LED 0")
        assert frame.mean() > 0.5
        assert capture.grabs == 3 and camera.frames_read == 8


def test_read_fresh_gives_up_naming_the_reason():
    capture = FakeCapture([coded_frame(10)])
    stale = "stale frame for LED 4: after discarding 2 buffered frames, 4 more were still stale \\(still dark\\)"
    with (RigCamera(0, backend="v4l2", flush_frames=2, max_stale_frames=3, open_capture=opener(capture)) as camera,
          pytest.raises(RigError, match=stale)):
        camera.read_fresh(lambda f: "still dark", "LED 4")


def side_lit(azimuth, size=32, level=0.5, dark=0.02):
    """A frame lit from ``azimuth``: brighter toward it (a plane of irradiance)."""
    x = (np.arange(size) - (size - 1) / 2) / (size / 2)
    xx, yy = np.meshgrid(x, -x)
    return (dark + level * (1 + 0.4 * (xx * math.cos(azimuth) + yy * math.sin(azimuth)))).astype(np.float32)


def test_frame_check_moments_and_decisions():
    azimuths = np.arange(8) * math.pi / 4
    check = FrameCheck(azimuths)
    dark = np.full((32, 32), 0.02, np.float32)
    up = side_lit(math.pi / 2) - dark
    assert check.moment(up, np.array([0.0, 1.0])) > 0.05  # lit from above: the moment points up
    assert abs(check.moment(up, np.array([1.0, 0.0]))) < 1e-6
    # a cloth whose texture is much brighter on its left than the LEDs' fall-off: it cancels in the change
    texture = np.where(np.arange(32) < 10, 1.0, 0.3)[None, :].astype(np.float32)
    led1, led2 = side_lit(azimuths[1]) * texture, side_lit(azimuths[2]) * texture
    assert check.reason(led2, 2, led1, dark, previous_led=1) is None  # adjacent LEDs are told apart
    noisy = led1 + np.random.default_rng(0).normal(0, 0.004, led1.shape).astype(np.float32)
    assert "not brighter toward LED 2 than LED 1" in check.reason(noisy, 2, led1, dark, previous_led=1)
    assert "repeats the previous one" in check.reason(led1, 2, led1, dark, previous_led=1)
    assert "too dark" in check.reason(dark + 0.001, 0, dark, dark)
    assert check.accepts(led2, 2, dark, dark)  # the first LED after the dark frame
    assert "than the dark frame" in check.reason(side_lit(azimuths[6]), 2, dark, dark)  # the wrong side
    assert check.dark_reason(dark, led2) is None
    assert "LEDs still seem on" in check.dark_reason(led2, led2)
    with pytest.raises(RigError):
        FrameCheck([])
