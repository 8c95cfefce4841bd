"""Overlay video (atomic cv2.VideoWriter) and the live window (dope_hope.io.video)."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
from video_files import read_video

from dope_hope.io import video as video_mod
from dope_hope.io.video import LiveWindow, OverlayVideo, display_problem


def frame(level: int) -> np.ndarray:
    return np.full((48, 64, 3), level, np.uint8)


def test_overlay_video_is_renamed_on_close_with_repeats(tmp_path):
    out = OverlayVideo(tmp_path / "sub" / "clip.overlay", fps=12.0)
    assert out.close() is None  # no frame, no file
    out.write(frame(30))
    out.repeat_last(2)  # two dropped frames: the last overlay stands in for them
    out.write(frame(200))
    assert list((tmp_path / "sub").iterdir())[0].name.startswith(".clip.overlay.")  # still temporary
    path = out.close()
    assert path.parent == tmp_path / "sub" and path.name in ("clip.overlay.mp4", "clip.overlay.avi")
    assert [p.name for p in (tmp_path / "sub").iterdir()] == [path.name]
    frames = read_video(path)
    assert len(frames) == 4 and out.frames == 4
    np.testing.assert_allclose([np.median(f) for f in frames], [30, 30, 30, 200], atol=6)
    assert abs(cv2.VideoCapture(str(path)).get(cv2.CAP_PROP_FPS) - 12.0) < 1e-6


def test_overlay_video_discard_leaves_nothing(tmp_path):
    out = OverlayVideo(tmp_path / "clip.overlay", fps=30.0)
    out.write(frame(10))
    out.discard()
    assert list(tmp_path.iterdir()) == []


def test_no_codec_is_a_one_line_error(tmp_path, monkeypatch):
    from dope_hope.errors import ConfigError

    monkeypatch.setattr(video_mod, "VIDEO_CODECS", ((".mp4", "ZZZZ"),))
    out = OverlayVideo(tmp_path / "clip.overlay", fps=30.0)
    with pytest.raises(ConfigError, match="--no-overlay"):
        out.write(frame(10))
    assert list(tmp_path.iterdir()) == []


def test_display_problem(monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr("sys.platform", "linux")
    assert "no display" in display_problem()
    monkeypatch.setenv("DISPLAY", ":0")
    monkeypatch.setattr(cv2, "getBuildInformation", lambda: "  GUI:                           NONE\n")
    assert "no GUI support" in display_problem()
    monkeypatch.setattr(cv2, "getBuildInformation", lambda: "  GUI:                           GTK3\n")
    assert display_problem() is None


def test_live_window_stops_on_q_or_when_closed(monkeypatch):
    shown, keys, visible = [], [-1, ord("q")], [1.0]
    monkeypatch.setattr(cv2, "imshow", lambda title, img: shown.append((title, img[0, 0].tolist())))
    monkeypatch.setattr(cv2, "waitKey", lambda ms: keys.pop(0))
    monkeypatch.setattr(cv2, "getWindowProperty", lambda title, prop: visible[0])
    monkeypatch.setattr(cv2, "destroyWindow", lambda title: shown.append(("closed", title)))
    win = LiveWindow("w")
    rgb = np.zeros((4, 4, 3), np.uint8)
    rgb[..., 0] = 255
    assert win.show(rgb) is True
    assert shown[0] == ("w", [0, 0, 255])  # shown as BGR
    assert win.show(rgb) is False  # q
    visible[0] = 0.0
    assert win.show(rgb) is False  # the user closed the window
    win.close()
    assert shown[-1] == ("closed", "w")
