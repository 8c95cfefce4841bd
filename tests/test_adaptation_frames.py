"""The unlabelled frames adapt reads (dope_hope.adaptation.frames): a video with its camera and
a folder of depth images, a folder of RGB-D frames; what lacks depth is refused in one line."""
from __future__ import annotations

import numpy as np
import pytest
from video_files import write_video

from dope_hope.adaptation.frames import open_unlabelled
from dope_hope.errors import ConfigError, InputFileError
from dope_hope.geometry import intrinsics_matrix
from dope_hope.io.camera import ImageCamera
from dope_hope.io.images import write_depth_mm, write_rgb

K = intrinsics_matrix(100.0, 100.0, 31.5, 23.5)
CAMERA = ImageCamera(K=K, width=64, height=48, source=None)


def frames(n: int = 3) -> list[np.ndarray]:
    return [np.full((48, 64, 3), 40 * (i + 1), np.uint8) for i in range(n)]


def test_a_video_takes_the_ith_depth_image(tmp_path):
    video = write_video(tmp_path / "clip.mp4", frames())
    depth = tmp_path / "depth"
    depth.mkdir()
    for i in range(3):
        write_depth_mm(depth / f"{i:04d}.png", np.full((48, 64), 0.5 + 0.1 * i))
    got = [g.load() for g in open_unlabelled([str(video)], CAMERA, depth).grab()]
    assert [f.index for f in got] == [0, 1, 2]
    assert [float(np.median(f.depth)) for f in got] == pytest.approx([0.5, 0.6, 0.7])
    assert np.allclose(got[0].K, K)


def test_a_video_needs_its_depth_and_camera(tmp_path):
    video = write_video(tmp_path / "clip.mp4", frames())
    with pytest.raises(ConfigError, match="a video holds no depth"):
        open_unlabelled([str(video)], CAMERA, None)
    (tmp_path / "few").mkdir()
    write_depth_mm(tmp_path / "few" / "0000.png", np.full((48, 64), 0.5))
    with pytest.raises(InputFileError, match="1 depth images for the 3 frames"):
        open_unlabelled([str(video)], CAMERA, tmp_path / "few")


def test_images_need_their_depth(tmp_path):
    write_rgb(tmp_path / "000000.png", frames(1)[0])
    with pytest.raises(InputFileError, match="no registered depth image"):
        open_unlabelled([str(tmp_path)], CAMERA)
    with pytest.raises(ConfigError, match="--depth DIR is for a video"):
        open_unlabelled([str(tmp_path)], CAMERA, tmp_path)
