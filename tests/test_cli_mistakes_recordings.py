"""Robot recordings that lie, through `dope-hope infer`: a camera that changes midway, stamps
that tie, depth of another frame or size, stamps before 1970 or a jump of decades, an image
folder with a metadata.yaml of its own, `infer .` inside a bag folder, a poses folder holding a
user's file, Ctrl-C while waiting for the Foxglove app. Each gives the frames' own result (with
a warning naming what was assumed) or one line, exit 2, nothing written.
"""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import test_cli_recordings
from ros_recordings import COLOUR, DEPTH, FRAME_ID, T0_NS, write_recording
from test_cli_recordings import assert_same, one_line_error, run_cli

from dope_hope.assets import DEMO_WEIGHTS
from dope_hope.io.images import write_depth_mm, write_rgb

pytestmark = pytest.mark.skipif(not DEMO_WEIGHTS.is_file(), reason="the demo model is not in this installation")
SECOND = 1_000_000_000
scenes = test_cli_recordings.scenes  # the rendered demo scenes (a module fixture)


def half_size(rgb: np.ndarray, depth: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The frame at half its size, and its K (pixel centres at integers: c' = (c + 0.5) / 2 - 0.5)."""
    h, w = rgb.shape[:2]
    K2 = K.copy()
    K2[:2, :2] /= 2
    K2[:2, 2] = (K[:2, 2] + 0.5) / 2 - 0.5
    return (cv2.resize(rgb, (w // 2, h // 2), interpolation=cv2.INTER_AREA),
            cv2.resize(depth, (w // 2, h // 2), interpolation=cv2.INTER_NEAREST), K2)


def image_records(frames: list[tuple[np.ndarray, np.ndarray]], Ks: list[np.ndarray], tmp_path, capsys) -> list:
    """Per frame, `infer` on the frame as a PNG with its own K.json and depth."""
    out = []
    for i, ((rgb, depth), K) in enumerate(zip(frames, Ks)):
        folder = tmp_path / f"image{i}"
        write_rgb(folder / "f.png", rgb)
        write_depth_mm(folder / "f.depth.png", depth)
        (folder / "K.json").write_text(json.dumps({"K": K.tolist()}))
        code, recs, err = run_cli([folder / "f.png", "--camera", folder / "K.json", "--depth", folder / "f.depth.png",
                                   "--out", folder / "out", "--fast"], capsys)  # a recording's preset
        assert code == 0, err
        out.append(recs)
    return out


def warnings_of(err: str) -> list[str]:
    return [line for line in err.splitlines() if ": warning: " in line]


# ----------------------------------------------------------------------------- the camera of each frame
@pytest.mark.parametrize("kind, name", [("ros1", "robot.bag"), ("ros2-mcap", "robot")])
def test_each_frame_is_read_with_the_camera_info_of_its_own_stamp(kind, name, scenes, tmp_path, capsys):
    """A camera that drops to half its size midway (its K with it): each frame's poses are the
    poses of that frame as an image with its own K, as image_transport pairs them."""
    (a, da), (b, db), (c, dc) = scenes["frames"]
    K = scenes["K"]
    b2, db2, K2 = half_size(b, db, K)
    frames, Ks = [(a, da), (b2, db2), (c, dc)], [K, K2, K]
    rec = write_recording(tmp_path / name, kind, frames, np.stack(Ks))
    code, records, err = run_cli([rec, "--out", tmp_path / "res"], capsys)
    assert code == 0, err
    assert warnings_of(err) == []
    assert_same(records, image_records(frames, Ks, tmp_path, capsys))


def test_a_camera_info_without_size_for_frames_of_two_sizes_is_refused(scenes, tmp_path, capsys):
    (a, da), (b, db), _ = scenes["frames"]
    b2, db2, _ = half_size(b, db, scenes["K"])
    rec = write_recording(tmp_path / "robot.bag", "ros1", [(a, da), (b2, db2)], scenes["K"], info_size=False)
    code, _, err = run_cli([rec, "--out", tmp_path / "res"], capsys)
    line = one_line_error(code, err)
    assert (f"{rec} topic /camera/color/camera_info: the camera states no image size and robot.bag#000001 "
            "is 160x120, the image robot.bag#000000 320x240: a K is the K of one size") in line
    assert not (tmp_path / "res").exists()
    given = scenes["images"] / "K.json"  # a K without a size, given for the recording's
    code, _, err = run_cli([rec, "--camera", given, "--out", tmp_path / "res"], capsys)
    assert f"{given}: the camera states no image size and robot.bag#000001 is 160x120" in one_line_error(code, err)
    assert not (tmp_path / "res").exists()


def test_a_camera_that_changes_without_an_info_of_the_images_stamp_is_refused(scenes, tmp_path, capsys):
    """Two different cameras, neither stamped as the images are: which took them is unknown."""
    from ros_recordings import INFO, info_message

    (a, da), (b, db), _ = scenes["frames"]
    K2 = scenes["K"].copy()
    K2[0, 0] *= 1.1

    def other(T, ros1, rgb, stamp):
        return info_message(T, ros1, K2, rgb.shape[1::-1], stamp + 1)

    rec = write_recording(tmp_path / "robot.bag", "ros1", [(a, da), (b, db)], scenes["K"], info=False,
                          extra=[(INFO, lambda T, ros1, rgb, stamp: info_message(T, ros1, scenes["K"],
                                                                                 rgb.shape[1::-1], stamp - 1)),
                                 (INFO, other)])
    code, _, err = run_cli([rec, "--out", tmp_path / "res"], capsys)
    line = one_line_error(code, err)
    assert (f"{rec} topic {INFO}: no CameraInfo stamped {T0_NS / 1e9:.9f} s, the stamp of an image, and the camera "
            "changes within the recording (2 different ones)") in line
    assert not (tmp_path / "res").exists()


# ----------------------------------------------------------------------------- stamps that tie
@pytest.mark.parametrize("stamps, warning", [
    ([0, 0, 0], f"every {COLOUR} message has the header stamp 0.000000 s: the frames are taken in recorded "
                f"order, paired with {DEPTH} in recorded order"),
    ([T0_NS, T0_NS, T0_NS + SECOND], f"1 {COLOUR} message(s) repeat an earlier header stamp (first: "
                                     f"{T0_NS / 1e9:.6f} s), paired with {DEPTH} in recorded order"),
])
def test_colour_frames_that_share_a_stamp_take_their_own_depth_in_recorded_order(stamps, warning, scenes, tmp_path,
                                                                                 capsys):
    frames = scenes["frames"]
    rec = write_recording(tmp_path / "robot.mcap", "mcap", frames, scenes["K"], stamps=stamps)
    code, records, err = run_cli([rec, "--out", tmp_path / "res"], capsys)
    assert code == 0, err
    assert warnings_of(err) == [f"dope-hope infer: warning: {rec}: {warning}"]
    assert all(r["ls_applied"] for r in records)
    assert_same(records, image_records(frames, [scenes["K"]] * 3, tmp_path, capsys))


# ----------------------------------------------------------------------------- depth of another frame, size
def test_depth_of_another_optical_frame_is_refused_unless_named(scenes, tmp_path, capsys):
    raw = "/camera/depth/image_rect_raw"
    rec = write_recording(tmp_path / "robot.bag", "ros1", scenes["frames"][:2], scenes["K"], depth_topic=raw,
                          depth_frame_id="camera_depth_optical_frame")
    code, _, err = run_cli([rec, "--out", tmp_path / "res"], capsys)
    line = one_line_error(code, err)
    assert (f"{rec} topic {raw}: not registered to colour (its frame_id is 'camera_depth_optical_frame', the colour "
            f"images' '{FRAME_ID}'); name a depth topic aligned to colour with --depth-topic") in line
    assert not (tmp_path / "res").exists()
    code, records, err = run_cli([rec, "--depth-topic", raw, "--out", tmp_path / "named"], capsys)
    assert code == 0, err
    assert warnings_of(err) == [f"dope-hope infer: warning: {rec} topic {raw}: its frame_id is "
                                f"'camera_depth_optical_frame', the colour images' '{FRAME_ID}'; used as registered "
                                "to colour because --depth-topic names it"]


def test_depth_smaller_than_colour_names_the_depth_topic(scenes, tmp_path, capsys):
    frames = [(rgb, half_size(rgb, d, scenes["K"])[1]) for rgb, d in scenes["frames"][:2]]
    rec = write_recording(tmp_path / "robot.bag", "ros1", frames, scenes["K"])
    code, _, err = run_cli([rec, "--out", tmp_path / "res"], capsys)
    line = one_line_error(code, err)
    assert (f"{rec} topic {DEPTH}: not registered to colour (its images are 160x120, the colour images 320x240)"
            in line)
    assert "camera_info" not in line
    assert not (tmp_path / "res").exists()


# ----------------------------------------------------------------------------- stamps far apart
def test_stamps_before_1970_are_refused_and_nothing_is_left(scenes, tmp_path, capsys):
    stamps = [-5 * SECOND, -5 * SECOND + SECOND // 10]
    rec = write_recording(tmp_path / "robot.mcap", "mcap", scenes["frames"][:2], scenes["K"], stamps=stamps)
    code, _, err = run_cli([rec, "--out", tmp_path / "res"], capsys)
    line = one_line_error(code, err)
    assert "robot.mcap#000000: header stamp -5.000000000 s is before 1970" in line
    assert not (tmp_path / "res").exists()


def test_realtime_does_not_wait_for_a_jump_of_the_stamps(scenes, tmp_path, capsys):
    """Sim time, then a stamp a minute later (wall-clock time: decades later, which a test would
    wait for as long): played at once, with a warning."""
    import time

    stamps = [10 * SECOND, 70 * SECOND]
    rec = write_recording(tmp_path / "robot.bag", "ros1", scenes["frames"][:2], scenes["K"], stamps=stamps)
    start = time.monotonic()
    code, records, err = run_cli([rec, "--realtime", "--out", tmp_path / "res"], capsys)
    assert code == 0, err
    assert time.monotonic() - start < 45  # not the 60 s of the stamps
    assert warnings_of(err) == ["dope-hope infer: warning: robot.bag: frame 1 is stamped +60.000 s from the one "
                                "before (more than 10 s either way): --realtime plays it at once and paces from there"]
    assert "2 frame(s) read" in err


# ----------------------------------------------------------------------------- names and folders
def test_an_image_folder_with_its_own_metadata_yaml_is_read_as_images(scenes, tmp_path, capsys):
    folder = tmp_path / "shots"
    write_rgb(folder / "a.png", scenes["frames"][0][0])
    (folder / "metadata.yaml").write_text("camera: kitchen\nauthor: me\n")
    code, records, err = run_cli([folder, "--camera", scenes["images"] / "K.json", "--out", tmp_path / "res"], capsys)
    assert code == 0, err
    assert records and all(r["image"].endswith("a.png") for r in records)


def test_infer_dot_inside_a_bag_folder_names_the_folder(scenes, tmp_path, capsys, monkeypatch):
    rec = write_recording(tmp_path / "robot", "ros2-mcap", scenes["frames"][:1], scenes["K"])
    monkeypatch.chdir(rec)
    code, records, err = run_cli([".", "--out", tmp_path / "res"], capsys)
    assert code == 0, err
    assert records and all(r["image"] == "robot#000000" for r in records)
    assert (tmp_path / "res" / "robot_poses" / "robot_poses.mcap").is_file()
    assert "dope-hope infer: robot: 1 frame(s)" in err


def test_a_poses_folder_holding_a_users_file_is_not_replaced(scenes, tmp_path, capsys):
    rec = write_recording(tmp_path / "robot.bag", "ros1", scenes["frames"][:1], scenes["K"])
    mine = tmp_path / "res" / "robot_poses" / "notes.txt"
    mine.parent.mkdir(parents=True)
    mine.write_text("mine")
    code, _, err = run_cli([rec, "--out", tmp_path / "res"], capsys)
    line = one_line_error(code, err)
    assert (f"{mine.parent}: holds notes.txt, which a poses bag does not: not replaced (another --out, or move it "
            "away)") in line
    assert mine.read_text() == "mine" and sorted(p.name for p in (tmp_path / "res").iterdir()) == ["robot_poses"]
    code, _, err = run_cli([rec, "--out", tmp_path / "again"], capsys)  # a bag written here is replaced
    assert code == 0, err
    code, _, err = run_cli([rec, "--out", tmp_path / "again"], capsys)
    assert code == 0, err


def test_ctrl_c_while_waiting_for_the_foxglove_app_leaves_no_folder(scenes, tmp_path, capsys, monkeypatch):
    from dope_hope.ros.foxglove_live import FoxgloveLive

    def interrupted(self, timeout_s=None):
        raise KeyboardInterrupt

    monkeypatch.setattr(FoxgloveLive, "wait_for_client", interrupted)
    rec = write_recording(tmp_path / "robot.bag", "ros1", scenes["frames"][:1], scenes["K"])
    code, _, err = run_cli([rec, "--foxglove", "0", "--out", tmp_path / "deep" / "res"], capsys)
    assert code == 130 and err.strip().endswith("dope-hope infer: interrupted"), err
    assert not (tmp_path / "deep").exists()
