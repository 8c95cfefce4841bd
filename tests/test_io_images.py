"""dope_hope.io.images: RGB/depth round trips, EXR reading (NViSII samples), header sizes."""
from __future__ import annotations

import numpy as np
import pytest

from dope_hope.errors import InputFileError
from dope_hope.io.images import (
    image_size,
    read_depth_m,
    read_image_raw,
    read_rgb,
    write_depth_mm,
    write_rgb,
)


def test_rgb_round_trip_keeps_channel_order(tmp_path):
    rgb = np.zeros((4, 6, 3), np.uint8)
    rgb[..., 0] = 200  # red
    write_rgb(tmp_path / "a.png", rgb)
    np.testing.assert_array_equal(read_rgb(tmp_path / "a.png"), rgb)
    assert image_size(tmp_path / "a.png") == (6, 4)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.png"]


def test_depth_mm_round_trip(tmp_path):
    d = np.array([[0.5, 1.2345], [np.nan, -1.0]], np.float32)
    write_depth_mm(tmp_path / "d.png", d)
    np.testing.assert_allclose(read_depth_m(tmp_path / "d.png"), [[0.5, 1.234], [0.0, 0.0]], atol=1e-3)
    assert read_image_raw(tmp_path / "d.png").dtype == np.uint16


def test_nvisii_exr_depth_and_segmentation(shared_data):
    folder = shared_data / "dope_format_samples" / "nvisii"
    depth = read_depth_m(folder / "00000.depth.exr")
    assert depth.shape == (500, 500) and depth.dtype == np.float32
    # background pixels hold -FLT_MAX in the file: read as 0 ("no measurement")
    assert np.isfinite(depth).all() and depth.min() == 0.0
    assert 1.0 < depth[depth > 0].min() and depth.max() == pytest.approx(2.2176938)
    seg = read_image_raw(folder / "00000.seg.exr")
    assert seg.shape == (500, 500, 4) and seg.dtype == np.float32
    ids = np.unique(seg[..., 0])
    assert ids[0] == 1.0 and 6.0 in ids and ids[-1] > 1e30  # background sentinel


@pytest.mark.parametrize("name, content", [("x.png", None), ("x.png", b"garbage"),
                                           ("x.exr", b"garbage")])
def test_unreadable_images_name_the_file(tmp_path, name, content):
    path = tmp_path / name
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(InputFileError) as err:
        read_image_raw(path)
    assert str(path) in str(err.value)
    with pytest.raises(InputFileError):
        image_size(path)


def test_collect_images_takes_every_image_suffix_and_skips_auxiliary_images(tmp_path):
    """One IMAGE_SUFFIXES for infer's folders, synth's backgrounds and INT8 calibration:
    a folder's .webp counts; depth / segmentation images and hidden files do not."""
    from dope_hope.io.images import IMAGE_SUFFIXES, collect_images, image_files

    for name in ("a.png", "b.webp", "a.depth.png", "a.seg.png", ".hidden.png", "notes.txt"):
        (tmp_path / name).write_bytes(b"")
    assert ".webp" in IMAGE_SUFFIXES
    assert [name for _, name in collect_images([str(tmp_path)])] == ["a.png", "b.webp"]
    assert (tmp_path / "b.webp") in image_files(tmp_path)
