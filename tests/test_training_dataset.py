"""dope_hope.training.dataset: augmentation keeps keypoints on their pixels, padding, skipping bad files,
determinism, keypoint order, sampler."""
from __future__ import annotations

import logging
import pickle
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from dope_hope.annotation import FrameAnnotation, ObjectAnnotation
from dope_hope.errors import ConfigError, InputFileError
from dope_hope.geometry import (
    LEGACY_TO_MESH,
    cuboid_keypoints,
    intrinsics_matrix,
    legacy_keypoints_to_current,
    project_points,
    scale_intrinsics,
)
from dope_hope.io.dope_json import write_dope_json
from dope_hope.io.images import write_rgb
from dope_hope.maps.grid import image_to_map
from dope_hope.preprocess import PAD_RGB
from dope_hope.training.augment import AugmentParams, augment, photometric_jitter
from dope_hope.training.dataset import (
    DopeDataset,
    EpochSampler,
    collate,
    convert_keypoint_order,
    scan_frames,
    split_records,
)
from dope_hope.training.frame_cache import FrameCache

torch.set_num_threads(1)
SIZE = np.array([0.06, 0.15, 0.04])
GEOMETRIC_ONLY = dict(brightness=0, contrast=0, saturation=0, hue=0, noise_std=0, blur_prob=0)


def write_frames(folder: Path, n: int, wh=(96, 72), cls="Ketchup", seed=0, order="dope-current") -> list[np.ndarray]:
    """n frames with random images and one projected cuboid each; returns their keypoints."""
    rng = np.random.default_rng(seed)
    W, H = wh
    K = intrinsics_matrix(1.2 * W, 1.2 * W, (W - 1) / 2, (H - 1) / 2)
    out = []
    for i in range(n):
        R = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
        t = np.array([rng.uniform(-0.03, 0.03), rng.uniform(-0.03, 0.03), rng.uniform(0.4, 0.5)])
        kp = project_points(cuboid_keypoints(SIZE), K, R, t)
        if order == "dope-legacy":  # the same box listed in the legacy frame's corner order
            size_legacy = np.abs(LEGACY_TO_MESH.T) @ SIZE
            kp = project_points(cuboid_keypoints(size_legacy) @ LEGACY_TO_MESH.T, K, R, t)
        write_rgb(folder / f"{i:06d}.png", rng.integers(0, 255, (H, W, 3), dtype=np.uint8))
        obj = ObjectAnnotation(cls, R, t, kp, 1.0, keypoint_order=order)
        other = ObjectAnnotation("Mustard", R, t + 0.01, kp + 3.0, 1.0)
        write_dope_json(folder / f"{i:06d}.json",
                        FrameAnnotation(folder / f"{i:06d}.json", K, W, H, [obj, other]))
        out.append(project_points(cuboid_keypoints(SIZE), K, R, t))
    return out


def dot_image(hw, keypoints, colours, radius=4):
    img = np.full((*hw, 3), 30, np.uint8)
    for (u, v), c in zip(keypoints, colours):
        cv2.circle(img, (int(round(u)), int(round(v))), radius, tuple(int(x) for x in c), -1)
    return img


# ----------------------------------------------------------------------------- augmentation
@pytest.mark.parametrize("src_hw", [(150, 200), (480, 640), (40, 52)])
def test_augmentation_keeps_keypoints_on_their_dots(src_hw):
    rng = np.random.default_rng(1)
    H, W = src_hw
    n = 9
    gx, gy = np.meshgrid(np.linspace(0.15 * W, 0.85 * W, 3), np.linspace(0.15 * H, 0.85 * H, 3))
    kp = (np.stack([gx.ravel(), gy.ravel()], 1) + rng.uniform(-0.05, 0.05, (n, 2)) * [W, H]).round()
    colours = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255], [255, 255, 0], [255, 0, 255],
                        [0, 255, 255], [255, 128, 0], [128, 0, 255], [255, 255, 255]])
    radius = max(4, int(0.03 * W))
    img = dot_image(src_hw, kp, colours, radius)
    d = np.linalg.norm(kp[:, None] - kp[None], axis=2) + np.eye(n) * 1e9
    separate = d.min(1) > 2 * radius + 2  # dots painted over by a neighbour are not checked
    params = AugmentParams(scale=(0.7, 1.4), rotation_deg=45, translate=0.15, **GEOMETRIC_ONLY)
    checked = 0
    for seed in range(6):
        out, kp2, M = augment(img, kp[None], (96, 128), params, np.random.default_rng(seed))
        assert out.shape == (96, 128, 3) and out.dtype == np.uint8
        s = np.sqrt(abs(np.linalg.det(M[:, :2])))
        for (u, v), c, ok in zip(kp2[0], colours, separate):
            if not ok or not (2 <= u <= 125 and 2 <= v <= 93) or radius * s < 1.5:
                continue
            got = out[int(round(v)), int(round(u))].astype(int)
            assert np.abs(got - c).max() <= 40, (seed, u, v, got, c)
            checked += 1
    assert checked >= 20


def test_fit_only_transform_is_a_resize_with_the_pixel_centre_convention():
    rng = np.random.default_rng(0)
    img = rng.integers(0, 255, (24, 32, 3), dtype=np.uint8)
    kp = np.array([[[0.0, 0.0], [31.0, 23.0], [10.5, 7.25]] + [[5.0, 5.0]] * 6])
    out, kp2, _ = augment(img, kp, (48, 64), AugmentParams(enabled=False, upscale=True), None)
    ref = cv2.resize(img, (64, 48), interpolation=cv2.INTER_LINEAR)
    # identical inside; the outermost output pixels blend with the padding (resize replicates)
    assert np.abs(out[1:-1, 1:-1].astype(int) - ref[1:-1, 1:-1].astype(int)).max() <= 1
    K2 = scale_intrinsics(np.eye(3), 2.0, 2.0)  # u' = 2 (u + 0.5) - 0.5
    np.testing.assert_allclose(kp2[0], kp[0] * 2 + K2[:2, 2], atol=1e-9)


def test_small_images_are_padded_not_rejected():
    img = np.random.default_rng(0).integers(0, 255, (30, 40, 3), dtype=np.uint8)
    kp = np.array([[[0.0, 0.0]] * 8 + [[39.0, 29.0]]])
    out, kp2, _ = augment(img, kp, (64, 64), AugmentParams(enabled=False), None)
    # (63 - 39) / 2 = 12, (63 - 29) / 2 = 17: the image is copied, centred, at its own scale
    np.testing.assert_array_equal(out[17:47, 12:52], img)
    assert np.all(out[:17] == PAD_RGB) and np.all(out[:, :12] == PAD_RGB) and np.all(out[47:] == PAD_RGB)
    np.testing.assert_allclose(kp2[0, 8], [51.0, 46.0])
    # random augmentation of a small image works too
    out, _, _ = augment(img, kp, (64, 64), AugmentParams(), np.random.default_rng(3))
    assert out.shape == (64, 64, 3)


def test_photometric_jitter_changes_colours_but_not_geometry():
    img = dot_image((64, 64), [(32, 32)], [(200, 60, 60)], radius=6)
    params = AugmentParams(scale=(1, 1), rotation_deg=0, translate=0, brightness=0.4, hue=0.1, noise_std=0)
    out, kp2, _ = augment(img, np.array([[[32.0, 32.0]] * 9]), (64, 64), params, np.random.default_rng(5))
    np.testing.assert_allclose(kp2[0, 0], [32, 32])
    assert not np.array_equal(out[32, 32], img[32, 32])


def test_augment_config_is_validated():
    with pytest.raises(ConfigError, match="rotaton"):
        AugmentParams.from_config({"rotaton_deg": 3})
    with pytest.raises(ConfigError, match="fit"):
        AugmentParams.from_config({"fit": "stretch"})


# ----------------------------------------------------------------------------- dataset
def test_dataset_items_targets_and_keypoints(tmp_path):
    gt = write_frames(tmp_path, 3, wh=(96, 72))
    records, bad = scan_frames([tmp_path], "KETCHUP")  # case-insensitive; Mustard ignored
    assert not bad and len(records) == 3 and all(r.keypoints.shape == (1, 9, 2) for r in records)
    ds = DopeDataset(records, (64, 96), stride=8, sigma=1.0, radius=1.0, max_instances=3)
    item = ds[0]
    assert item["image"].shape == (3, 64, 96) and item["image"].dtype == torch.float32
    assert item["belief"].shape == (9, 8, 12) and item["affinity"].shape == (16, 8, 12)
    kp = item["keypoints"].numpy()
    assert kp.shape == (3, 9, 2) and np.isnan(kp[1:]).all()
    # fit only (no augmentation): 96x72 -> scale 8/9 into 96x64, keypoints mapped accordingly
    s = 64 / 72
    expect = s * (gt[0] - [47.5, 35.5]) + [47.5, 31.5]
    inside = (expect[:, 0] >= -0.5) & (expect[:, 0] < 95.5) & (expect[:, 1] >= -0.5) & (expect[:, 1] < 63.5)
    np.testing.assert_allclose(kp[0][inside], expect[inside], atol=1e-4)
    assert np.isnan(kp[0][~inside]).all()
    # the belief peak of the centroid sits on the centroid's map cell
    cx, cy = np.round(image_to_map(expect[8], 8)).astype(int)
    b = item["belief"][8].numpy()
    assert np.unravel_index(b.argmax(), b.shape) == (cy, cx)


def test_object_centred_crops_hold_the_object_and_keep_keypoints_on_their_dots():
    """augment.crop: training items are crops centred near an instance, at the scale of the
    whole-frame transform; the drawn dots stay under their keypoints."""
    hw_src, crop = (120, 160), (48, 64)
    rng = np.random.default_rng(3)
    colours = rng.integers(60, 255, (9, 3))
    params = AugmentParams.from_config({**GEOMETRIC_ONLY, "crop": list(crop), "crop_jitter": 0.1,
                                        "rotation_deg": 20.0, "scale": [0.9, 1.1]})
    for trial in range(20):
        grid = np.stack(np.meshgrid([-14.0, 0.0, 14.0], [-12.0, 0.0, 12.0]), -1).reshape(9, 2)
        kp = (grid[[0, 1, 2, 3, 5, 6, 7, 8, 4]] + [rng.uniform(25, 135), rng.uniform(20, 100)])[None]
        img = dot_image(hw_src, kp[0], colours, radius=3)
        out, kp_out, M = augment(img, kp, (96, 128), params, np.random.default_rng(trial))
        assert out.shape == (*crop, 3)
        centroid = kp_out[0, 8]
        # the centroid lies within crop_jitter of the crop's centre
        assert abs(centroid[0] - (crop[1] - 1) / 2) <= 0.1 * crop[1] + 1e-6
        assert abs(centroid[1] - (crop[0] - 1) / 2) <= 0.1 * crop[0] + 1e-6
        # scale of the whole-frame fit (96x128 from 120x160: 0.8) times the zoom: unchanged by the crop
        assert 0.8 * 0.9 - 1e-6 <= np.sqrt(abs(np.linalg.det(M[:, :2]))) <= 0.8 * 1.1 + 1e-6
        for (u, v), c in zip(kp_out[0], colours):
            if 1 <= u < crop[1] - 1 and 1 <= v < crop[0] - 1:
                np.testing.assert_allclose(out[int(round(v)), int(round(u))], c, atol=40)
    # frames that skip the random geometry (prob_geometric) are cropped around the object too
    plain = AugmentParams.from_config({**GEOMETRIC_ONLY, "crop": list(crop), "crop_jitter": 0.0,
                                       "prob_geometric": 0.0})
    _, kp_plain, _ = augment(img, kp, (96, 128), plain, np.random.default_rng(0))
    np.testing.assert_allclose(kp_plain[0, 8], [(crop[1] - 1) / 2, (crop[0] - 1) / 2], atol=1e-9)
    # validation items (no augmentation) are whole frames; a frame without instances still crops
    assert augment(img, kp, (96, 128), AugmentParams(enabled=False), None)[0].shape == (96, 128, 3)
    empty = augment(img, np.zeros((0, 9, 2)), (96, 128), params, np.random.default_rng(0))
    assert empty[0].shape == (*crop, 3)
    with pytest.raises(ConfigError, match="augment.crop"):
        AugmentParams.from_config({"crop": [50, 64]})


def test_dataset_trains_on_crops_and_validates_on_whole_frames(tmp_path):
    write_frames(tmp_path, 2, wh=(96, 72))
    records, _ = scan_frames([tmp_path], "Ketchup")
    aug = AugmentParams.from_config({"crop": [32, 48]})
    train = DopeDataset(records, (64, 96), stride=8, sigma=1.0, radius=1.0, augment=aug)
    val = DopeDataset(records, (64, 96), stride=8, sigma=1.0, radius=1.0)
    item = train[0]
    assert item["image"].shape == (3, 32, 48) and item["belief"].shape == (9, 4, 6)
    assert item["affinity"].shape == (16, 4, 6)
    assert val[0]["image"].shape == (3, 64, 96) and val[0]["belief"].shape == (9, 8, 12)
    assert collate([train[0], train[1]])["image"].shape == (2, 3, 32, 48)
    # a crop larger than the input is capped at the input size
    big = DopeDataset(records, (64, 96), stride=8, sigma=1.0, radius=1.0,
                      augment=AugmentParams.from_config({"crop": [128, 64]}))
    assert big[0]["image"].shape == (3, 64, 64)


def test_items_are_a_function_of_seed_epoch_and_index(tmp_path):
    write_frames(tmp_path, 2)
    records, _ = scan_frames([tmp_path], "Ketchup")
    ds = DopeDataset(records, (64, 64), 8, 1.0, 1.0, augment=AugmentParams(), seed=7)
    a, b = ds[(3, 1)], ds[(3, 1)]
    assert torch.equal(a["image"], b["image"]) and torch.equal(a["belief"], b["belief"])
    assert not torch.equal(a["image"], ds[(4, 1)]["image"])
    ds.set_epoch(3)
    assert torch.equal(ds[1]["image"], a["image"])


def test_legacy_keypoints_are_converted(tmp_path):
    gt = write_frames(tmp_path, 1, order="dope-legacy")
    records, _ = scan_frames([tmp_path], "ketchup")
    np.testing.assert_allclose(records[0].keypoints[0], gt[0], atol=1e-6)
    back = convert_keypoint_order(gt[0], "dope-current", "dope-legacy")
    np.testing.assert_allclose(convert_keypoint_order(back, "dope-legacy", "dope-current"), gt[0])
    with pytest.raises(ConfigError, match="keypoint order"):
        convert_keypoint_order(gt[0], "dope-2017", "dope-current")


def test_corrupt_json_is_reported_once_and_skipped(tmp_path, caplog):
    write_frames(tmp_path, 4)
    (tmp_path / "000001.json").write_text('{"objects": [ {"class": ')
    (tmp_path / "000002.json").write_text('{"format": "dope-hope", "objects": [{"class": "Ketchup"}]}')
    with caplog.at_level(logging.WARNING, logger="dope_hope.training.dataset"):
        records, bad = scan_frames([tmp_path], "Ketchup")
        scan_frames([tmp_path], "Ketchup")  # a second scan (e.g. train + val) stays quiet
    assert [r.json_path.name for r in records] == ["000000.json", "000003.json"]
    assert sorted(p.name for p, _ in bad) == ["000001.json", "000002.json"]
    warned = [r.getMessage() for r in caplog.records]
    assert len(warned) == 2 and any("000001.json" in m for m in warned) and any("000002.json" in m for m in warned)


def test_corrupt_image_is_reported_once_and_replaced(tmp_path, caplog):
    write_frames(tmp_path, 4)
    (tmp_path / "000002.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    records, _ = scan_frames([tmp_path], "Ketchup")
    ds = DopeDataset(records, (64, 64), 8, 1.0, 1.0)
    with caplog.at_level(logging.WARNING, logger="dope_hope.training.dataset"):
        batches = [collate([ds[i] for i in range(4)]) for _ in range(2)]
    assert len([r for r in caplog.records if "000002.png" in r.getMessage()]) == 1
    assert batches[0]["bad_files"] == [str(tmp_path / "000002.png")]
    assert torch.equal(batches[0]["image"][2], batches[0]["image"][3])  # frame 3 stands in
    assert batches[0]["image"].shape == (4, 3, 64, 64)
    # in a DataLoader worker the item carries the bad file up to the main process
    loader = torch.utils.data.DataLoader(ds, batch_size=4, num_workers=1, collate_fn=collate)
    assert next(iter(loader))["bad_files"] == [str(tmp_path / "000002.png")]


def test_missing_or_empty_folder_is_a_clear_error(tmp_path):
    with pytest.raises(InputFileError, match="not found"):
        scan_frames([tmp_path / "nope"], "Ketchup")
    with pytest.raises(InputFileError, match="no DOPE frames"):
        scan_frames([tmp_path], "Ketchup")


# ----------------------------------------------------------------------------- sampling
def test_epoch_sampler_order_shards_and_skip():
    s = EpochSampler(10, seed=3)
    s.set_epoch(2)
    order = [i for _, i in s]
    assert sorted(order) == list(range(10))
    s2 = EpochSampler(10, seed=3)
    s2.set_epoch(2)
    assert [i for _, i in s2] == order
    s2.set_epoch(3)
    assert [i for _, i in s2] != order
    s.set_epoch(2, skip=4)
    assert [i for _, i in s] == order[4:] and len(s) == 6
    shards = []
    for r in range(3):
        sr = EpochSampler(10, seed=3, rank=r, world_size=3)
        sr.set_epoch(2)
        shards.append([i for e, i in sr])
        assert all(e == 2 for e, _ in sr)
    assert all(len(x) == 4 for x in shards) and set(sum(shards, [])) == set(range(10))


def test_split_is_deterministic_and_disjoint(tmp_path):
    write_frames(tmp_path, 10)
    records, _ = scan_frames([tmp_path], "Ketchup")
    tr, va = split_records(records, 0.2, seed=1)
    tr2, va2 = split_records(records, 0.2, seed=1)
    assert [r.json_path for r in va] == [r.json_path for r in va2] and len(va) == 2 and len(tr) == 8
    assert not {r.json_path for r in tr} & {r.json_path for r in va}


def test_official_ndds_and_nvisii_samples(shared_data):
    """The official formats go through the same dataset (NViSII: legacy order converted)."""
    from dope_hope.io.dope_json import read_dope_json

    samples = shared_data / "dope_format_samples"
    records, bad = scan_frames([samples / "ndds"], "cracker")
    assert len(records) == 4 and not bad
    item = DopeDataset(records, (400, 400), 8, 2.0, 1.0)[0]
    assert item["belief"].shape == (9, 50, 50) and float(item["belief"].max()) > 0.9
    frame = read_dope_json(samples / "nvisii" / "00000.json")
    obj = next(o for o in frame.objects if o.class_name == "Shark")
    assert obj.keypoint_order == "dope-legacy"
    records, _ = scan_frames([samples / "nvisii"], "shark")
    np.testing.assert_allclose(records[0].keypoints[0], legacy_keypoints_to_current(obj.projected_cuboid))


def test_frame_cache_keeps_what_forked_workers_decode_and_changes_no_item(tmp_path):
    write_frames(tmp_path, 6)
    records, _ = scan_frames([tmp_path], "Ketchup")
    plain = DopeDataset(records, (64, 64), 8, 1.0, 1.0, augment=AugmentParams(), seed=7)
    cached = DopeDataset(records, (64, 64), 8, 1.0, 1.0, augment=AugmentParams(), seed=7, frame_cache_mb=1)
    assert cached.frame_cache.capacity == 6 and cached.frame_cache.kept == 0
    loader = torch.utils.data.DataLoader(cached, batch_size=3, num_workers=1, collate_fn=collate,
                                         multiprocessing_context="fork")
    assert sum(len(b["index"]) for b in loader) == 6
    assert cached.frame_cache.kept == 6  # decoded in the worker, kept for the parent and later workers
    want = [plain[(2, i)] for i in range(6)]
    for png in tmp_path.glob("*.png"):
        png.unlink()  # from here on only the cache can give the frames
    for i, item in enumerate(cached[(2, i)] for i in range(6)):
        assert torch.equal(item["image"], want[i]["image"]) and torch.equal(item["belief"], want[i]["belief"])
        assert item["bad_files"] == []


def test_frame_cache_holds_its_budget_and_only_frames_of_its_size():
    frame = np.arange(72 * 96 * 3, dtype=np.uint8).reshape(72, 96, 3)
    cache = FrameCache(10, (72, 96), budget_mb=2.5 * frame.nbytes / 2**20)
    assert cache.capacity == 2
    cache.put(0, frame)
    cache.put(1, frame[:64])  # another size: decoded every time instead
    cache.put(5, frame)  # beyond the budget
    assert cache.kept == 1 and cache.get(1) is None and cache.get(5) is None
    got = cache.get(0)
    got[:] = 0  # a copy: the kept frame stays as it was
    np.testing.assert_array_equal(cache.get(0), frame)
    spawned = pickle.loads(pickle.dumps(cache))  # a spawned worker cannot share the map
    assert spawned.capacity == 0 and spawned.get(0) is None
    assert FrameCache(10, (72, 96), budget_mb=0).capacity == 0


def test_sensor_noise_has_the_drawn_strength_and_differs_between_images():
    flat = np.full((128, 128, 3), 128, np.uint8)
    params = AugmentParams(brightness=0, contrast=0, saturation=0, hue=0, blur_prob=0, noise_std=8.0)
    outs = []
    for seed in (1, 2):
        std = np.random.default_rng(seed).uniform(0.0, 8.0)  # the jitter's only other draw is the offset
        out = photometric_jitter(flat, params, np.random.default_rng(seed))
        noise = out.astype(np.float64) - 128.0
        assert abs(noise.std() - std) < 0.05 * std + 0.3 and abs(noise.mean()) < 0.1 * std + 0.6
        outs.append(noise)
    assert not np.array_equal(outs[0], outs[1])
    big = np.full((1300, 1100, 3), 128, np.uint8)  # more pixels than the bank: fresh samples
    assert photometric_jitter(big, params, np.random.default_rng(3)).std() > 0
