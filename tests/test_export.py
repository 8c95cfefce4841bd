"""ONNX export: graphs reproduce PyTorch, metadata, Isaac ROS layout, INT8, CLI, bad options."""
from __future__ import annotations

import json

import numpy as np
import onnx
import pytest
import torch
from fitted_model import IMAGE_HW, fit_lite_checkpoint, scene
from scipy.spatial.transform import Rotation

from dope_hope.cli import main
from dope_hope.config import load_config
from dope_hope.errors import ConfigError, InputFileError
from dope_hope.export.compare import compare_maps
from dope_hope.export.int8 import calibration_images
from dope_hope.export.isaac_ros import ENCODERS as ISAAC_ENCODERS
from dope_hope.export.isaac_ros import (
    ISAAC_ROS_CURRENT,
    channel_order,
    cuboid_vertices,
    decode,
    dope_config_entry,
    isaac_ros_release,
)
from dope_hope.export.pipeline import Int8Calibration, export_checkpoint
from dope_hope.export.to_onnx import ExportSettings, export_model
from dope_hope.geometry import (
    CUBOID_CORNER_SIGNS,
    LEGACY_TO_MESH,
    cuboid_keypoints,
    mesh_rotation_to_legacy,
    project_points,
    rotation_error_deg,
)
from dope_hope.inference.onnx_backend import OnnxBackend, output_order
from dope_hope.io.images import write_rgb
from dope_hope.maps.targets import make_targets
from dope_hope.model.checkpoint import make_object_info, save_checkpoint
from dope_hope.model.network import IMAGENET_MEAN, IMAGENET_STD, build_model

torch.set_num_threads(1)

TOL = 1e-4  # absolute, fp32 maps


def _ckpt(config, class_name="Ketchup", frame="mesh"):
    """The checkpoint fields export needs (no file, no second model build)."""
    info = make_object_info(class_name, frame=frame)
    return {"config": config, "object": info,
            "keypoint_order": "dope-legacy" if frame == "legacy" else "dope-current",
            "normalization": {"mean": list(IMAGENET_MEAN), "std": list(IMAGENET_STD)}}


def _lite_config(hw=(64, 64), head=50):
    cfg = load_config("lite")
    cfg["model"]["head"] = head
    cfg["input"]["size"] = list(hw)
    return cfg


def _torch_maps(model, x: np.ndarray):
    with torch.inference_mode():
        b, a = model(torch.from_numpy(x))[-1]
    return b.numpy(), a.numpy()


@pytest.fixture(scope="module")
def lite():
    torch.manual_seed(1)
    cfg = _lite_config()
    model = build_model(cfg).eval()
    # Non-trivial BatchNorm statistics, so that eval-mode folding is actually exercised.
    for m in model.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.uniform_(-0.2, 0.2)
            m.running_var.uniform_(0.5, 2.0)
    for block in model.lite.stages:  # outputs of map scale (~1), not the near-zero init
        torch.nn.init.normal_(block[-1].weight, std=0.1)
    return model, _ckpt(cfg)


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    return fit_lite_checkpoint(tmp_path_factory.mktemp("fit") / "fitted.pt")


def test_lite_static_and_dynamic_exports_match_pytorch(lite, tmp_path):
    model, ckpt = lite
    rng = np.random.default_rng(0)
    info, verify = export_model(model, ckpt, tmp_path / "static.onnx", source="lite.pt")
    assert verify < TOL and info.fixed_input_hw == (64, 64)
    backend = OnnxBackend(tmp_path / "static.onnx", threads=1)
    x = rng.standard_normal((2, 3, 64, 64)).astype(np.float32)  # batch axis is dynamic
    for got, ref in zip(backend.run(x), _torch_maps(model, x)):
        assert got.shape == ref.shape and np.abs(got - ref).max() < TOL
    assert np.abs(_torch_maps(model, x)[0]).max() > 0.05  # the maps are not trivially ~0

    export_model(model, ckpt, tmp_path / "dyn.onnx", ExportSettings(dynamic=True))
    dyn = OnnxBackend(tmp_path / "dyn.onnx", threads=1)
    assert dyn.fixed_input_hw is None
    for hw in [(64, 64), (96, 160), (40, 56)]:
        x = rng.standard_normal((1, 3) + hw).astype(np.float32)
        got, ref = dyn.run(x), _torch_maps(model, x)
        assert got[0].shape == (1, 9, hw[0] // 8, hw[1] // 8)
        assert max(np.abs(g - r).max() for g, r in zip(got, ref)) < TOL
    assert not model.training  # export leaves the model's mode alone


def test_metadata_makes_the_file_self_describing(lite, tmp_path):
    model, ckpt = lite
    path = tmp_path / "m.onnx"
    export_model(model, ckpt, path, ExportSettings(input_hw=(48, 72), opset=17), source="lite.pt")
    proto = onnx.load(str(path))
    onnx.checker.check_model(proto)
    meta = {p.key: p.value for p in proto.metadata_props}
    assert meta["dope_hope.format"] == "dope-hope-onnx"
    assert meta["dope_hope.class_name"] == "Ketchup"
    np.testing.assert_allclose(json.loads(meta["dope_hope.size_m"]), [0.064514, 0.148608, 0.043368])
    assert meta["dope_hope.frame"] == "mesh" and meta["dope_hope.keypoint_order"] == "dope-current"
    np.testing.assert_allclose(json.loads(meta["dope_hope.mean"]), IMAGENET_MEAN)
    np.testing.assert_allclose(json.loads(meta["dope_hope.std"]), IMAGENET_STD)
    assert meta["dope_hope.stride"] == "8" and meta["dope_hope.head"] == "50"
    assert meta["dope_hope.layout"] == "native" and meta["dope_hope.opset"] == "17"
    assert json.loads(meta["dope_hope.fixed_input_hw"]) == [48, 72]
    assert json.loads(meta["dope_hope.input_hw"]) == [64, 64]  # the training size
    assert meta["dope_hope.version"] and "TorchScript" in meta["dope_hope.exporter"]
    assert json.loads(meta["dope_hope.config"])["model"]["arch"] == "lite"
    assert max(op.version for op in proto.opset_import if op.domain in ("", "ai.onnx")) == 17
    assert [i.name for i in proto.graph.input] == ["image"]
    assert [o.name for o in proto.graph.output] == ["belief", "affinity"]


def test_isaac_ros_layout_names_shapes_and_normalization(lite, tmp_path):
    model, ckpt = lite
    path = tmp_path / "isaac.onnx"
    info, _ = export_model(model, ckpt, path, ExportSettings(layout="isaac-ros", isaac_ros_version="3.1"))
    assert info.fixed_input_hw == (480, 640)  # dope_converter.py's default network size
    proto = onnx.load(str(path))
    dims = lambda v: [d.dim_value for d in v.type.tensor_type.shape.dim]  # noqa: E731
    assert [(i.name, dims(i)) for i in proto.graph.input] == [("input", [1, 3, 480, 640])]
    assert [(o.name, dims(o)) for o in proto.graph.output] == [("output", [1, 25, 60, 80])]
    meta = {p.key: p.value for p in proto.metadata_props}
    assert json.loads(meta["dope_hope.input_mean"]) == [0.5, 0.5, 0.5]  # 3.1's launch default
    assert json.loads(meta["dope_hope.isaac_ros.object_dimensions_cm"]) == pytest.approx(
        [6.4514, 14.8608, 4.3368])
    assert meta["dope_hope.isaac_ros.version"] == "3.1"

    # Fed a 0.5/0.5-normalized image, the graph reproduces the native maps (3.1: same order).
    import onnxruntime as ort

    rgb = np.random.default_rng(2).random((1, 3, 480, 640), dtype=np.float32)
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    (out,) = sess.run(None, {"input": (rgb - 0.5) / 0.5})
    mean, std = np.array(IMAGENET_MEAN, np.float32), np.array(IMAGENET_STD, np.float32)
    b, a = _torch_maps(model, ((rgb - mean[:, None, None]) / std[:, None, None]).astype(np.float32))
    assert np.abs(out[:, :9] - b).max() < TOL and np.abs(out[:, 9:] - a).max() < TOL

    # The current release: ImageNet encoder (an identity conversion) and Isaac's vertex order.
    info, _ = export_model(model, ckpt, tmp_path / "isaac_in.onnx",
                           ExportSettings(layout="isaac-ros", input_hw=(64, 64)))
    assert info.input_mean == ISAAC_ENCODERS["imagenet"][0]
    assert info.extra["isaac_ros.version"] == ISAAC_ROS_CURRENT
    x = ((rgb[:, :, :64, :64] - mean[:, None, None]) / std[:, None, None]).astype(np.float32)
    sess = ort.InferenceSession(str(tmp_path / "isaac_in.onnx"), providers=["CPUExecutionProvider"])
    (out,) = sess.run(None, {"input": x})
    b, a = _torch_maps(model, x)
    order = output_order(channel_order("mesh", isaac_ros_release(ISAAC_ROS_CURRENT)))
    assert order.tolist() != list(range(25))
    assert np.abs(out - np.concatenate([b, a], 1)[:, order]).max() < TOL
    # OnnxBackend puts the channels back in the model's order.
    got = OnnxBackend(tmp_path / "isaac_in.onnx", threads=1).run(x)
    assert np.abs(got[0] - b).max() < TOL and np.abs(got[1] - a).max() < TOL


# ----------------------------------------------------------------------------- Isaac ROS decoding
class ConstantMaps(torch.nn.Module):
    """A stand-in network whose last stage always returns the given (9, h, w), (16, h, w) maps."""

    def __init__(self, belief: np.ndarray, affinity: np.ndarray, stride: int):
        super().__init__()
        self.stride, self.head, self.arch = stride, 0, "constant"
        self.register_buffer("belief", torch.from_numpy(belief)[None])
        self.register_buffer("affinity", torch.from_numpy(affinity)[None])

    def forward(self, x):
        zero = x.mean() * 0  # keeps the input in the graph
        return [(self.belief + zero, self.affinity + zero)]


ISAAC_HW = (480, 640)
ISAAC_K = np.array([[600.0, 0.0, 319.5], [0.0, 600.0, 239.5], [0.0, 0.0, 1.0]])
ISAAC_R = Rotation.from_euler("xyz", [20, -30, 15], degrees=True).as_matrix()
ISAAC_T = np.array([0.031, -0.017, 0.52])


def _model_keypoints(frame: str) -> np.ndarray:
    """(9, 2) image px of the Ketchup box at the test pose, in the model's keypoint order."""
    size = np.asarray(make_object_info("Ketchup")["size_m"])
    if frame == "legacy":  # the same box in the legacy frame of the official weights
        return project_points(cuboid_keypoints(np.abs(LEGACY_TO_MESH).T @ size), ISAAC_K,
                              mesh_rotation_to_legacy(ISAAC_R), ISAAC_T)
    return project_points(cuboid_keypoints(size), ISAAC_K, ISAAC_R, ISAAC_T)


def _isaac_output(tmp_path, frame: str, stride: int, version: str):
    """(info, (1, 25, 60, 80) output of the exported graph) for maps of the box at the test pose."""
    import onnxruntime as ort

    belief, affinity = make_targets(_model_keypoints(frame)[None], ISAAC_HW, stride)
    path = tmp_path / f"{frame}_{stride}_{version}.onnx"
    info, _ = export_model(ConstantMaps(belief, affinity, stride), _ckpt({}, frame=frame), path,
                           ExportSettings(layout="isaac-ros", isaac_ros_version=version))
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    return info, sess.run(None, {"input": np.zeros((1, 3) + ISAAC_HW, np.float32)})[0]


@pytest.mark.parametrize("version,frame,stride", [
    ("3.1", "mesh", 8), ("3.1", "legacy", 8), ("3.2", "mesh", 8), ("4.0", "legacy", 8), ("4.0", "mesh", 4)])
def test_isaac_ros_publishes_the_mesh_frame_pose(tmp_path, version, frame, stride):
    """Isaac ROS's decoder (transcribed: dope_hope.export.isaac_ros.decode) on the exported output, with
    the printed dope_config.yaml dimensions, returns the mesh-frame pose of the box."""
    info, out = _isaac_output(tmp_path, frame, stride, version)
    assert out.shape == (1, 25, 60, 80) and info.stride == 8
    assert dope_config_entry(info.class_name, info.size_m) == '"Ketchup": [6.4514, 14.8608, 4.3368]'
    dims = json.loads(info.extra["isaac_ros.object_dimensions_cm"])
    poses = decode(out, ISAAC_K, dims, isaac_ros_release(version))
    assert len(poses) == 1
    R, t = poses[0]
    # Up to 3.1 the decoder's 5x5 window reads (x, y) as (row, col) and mostly falls back to
    # the integer peak (+-4 px): a coarser pose; 3.2+ refines on an 11x11 window.
    deg, mm = (3.0, 10.0) if version == "3.1" else (0.3, 1.0)
    assert rotation_error_deg(R, ISAAC_R) < deg and np.abs(t - ISAAC_T).max() * 1000 < mm


def test_isaac_ros_3_2_turned_the_vertex_order(tmp_path):
    """The channel order is what makes 3.2+ publish the mesh-frame pose: the model's own order
    (what a 3.1 export holds) read by 3.2 gives R_mesh Rz(180 deg)."""
    info, out = _isaac_output(tmp_path, "mesh", 8, "3.1")
    dims = json.loads(info.extra["isaac_ros.object_dimensions_cm"])
    (R, _), = decode(out, ISAAC_K, dims, isaac_ros_release("3.2"))
    Rz180 = np.diag([-1.0, -1.0, 1.0])
    assert rotation_error_deg(R, ISAAC_R @ Rz180) < 0.3 and rotation_error_deg(R, ISAAC_R) > 179
    # The vertex tables as the C++ source writes them (CuboidVertices: right/left, top/bottom).
    old, new = (np.sign(cuboid_vertices((2, 4, 6), isaac_ros_release(v)))[:, :8] for v in ("3.1", "3.2"))
    assert old.tolist() == [[1, -1, -1, 1, 1, -1, -1, 1], [-1, -1, 1, 1, -1, -1, 1, 1],
                            [1, 1, 1, 1, -1, -1, -1, -1]]
    assert np.array_equal(old.T, CUBOID_CORNER_SIGNS) and np.array_equal(new, Rz180 @ old)


def test_isaac_ros_lite_head_100_is_pooled_to_stride_8(tmp_path):
    cfg = _lite_config(head=100)  # stride-4 maps
    torch.manual_seed(3)
    model = build_model(cfg).eval()
    for block in model.lite.stages:
        torch.nn.init.normal_(block[-1].weight, std=0.1)
    path = tmp_path / "lite100.onnx"
    info, verify = export_model(model, _ckpt(cfg), path, ExportSettings(layout="isaac-ros", input_hw=(64, 64)))
    assert verify < TOL and info.stride == 8 and info.head == 100
    assert info.extra["isaac_ros.resampled_from_stride"] == "4"
    x = np.random.default_rng(4).standard_normal((1, 3, 64, 64)).astype(np.float32)
    got = OnnxBackend(path, threads=1).run(x)  # the model's order, stride 8
    ref = [torch.nn.functional.avg_pool2d(torch.from_numpy(m), 2).numpy() for m in _torch_maps(model, x)]
    assert got[0].shape == (1, 9, 8, 8) and max(np.abs(g - r).max() for g, r in zip(got, ref)) < TOL
    assert np.abs(ref[0]).max() > 0.05  # not trivially ~0


def test_isaac_ros_refuses_stride_1_dynamic_and_unknown_versions(tmp_path):
    belief, affinity = np.zeros((9, 64, 64), np.float32), np.zeros((16, 64, 64), np.float32)
    with pytest.raises(ConfigError, match="stride 1"):  # DOPE-DR-400: Isaac ROS's decoder scales by 8
        export_model(ConstantMaps(belief, affinity, 1), _ckpt({}), tmp_path / "x.onnx",
                     ExportSettings(layout="isaac-ros", input_hw=(64, 64)))
    lite = build_model(_lite_config()).eval()
    with pytest.raises(ConfigError, match="fixed input size"):
        export_model(lite, _ckpt(_lite_config()), tmp_path / "y.onnx", ExportSettings(layout="isaac-ros", dynamic=True))
    for bad in ("three", "1.0", "3"):
        with pytest.raises(ConfigError, match="isaac-ros-version"):
            export_model(lite, _ckpt(_lite_config()), tmp_path / "z.onnx",
                         ExportSettings(layout="isaac-ros", isaac_ros_version=bad))
    assert not list(tmp_path.iterdir())  # nothing written


def test_dope_dr_50_export_matches_pytorch(tmp_path):
    torch.manual_seed(0)
    cfg = load_config("dope_dr_50")
    model = build_model(cfg).eval()
    info, verify = export_model(model, _ckpt(cfg, frame="legacy"), tmp_path / "dr50.onnx",
                                ExportSettings(input_hw=(64, 64)))
    assert info.arch == "dope" and info.stride == 8 and info.keypoint_order == "dope-legacy"
    backend = OnnxBackend(tmp_path / "dr50.onnx", threads=1)
    x = np.random.default_rng(3).standard_normal((1, 3, 64, 64)).astype(np.float32)
    got, ref = backend.run(x), _torch_maps(model, x)
    assert got[0].shape == (1, 9, 8, 8) and got[1].shape == (1, 16, 8, 8)
    assert max(np.abs(g - r).max() for g, r in zip(got, ref)) < TOL


def test_int8_export_stays_close_to_fp32(fitted, tmp_path):
    calib = tmp_path / "calib"
    rgb, _ = scene()
    rng = np.random.default_rng(0)
    for i in range(4):  # the scene under photometric jitter + two unrelated images
        img = np.clip(rgb.astype(int) + rng.integers(-20, 20, rgb.shape), 0, 255).astype(np.uint8)
        write_rgb(calib / f"{i:06d}.png", img if i < 2 else np.roll(img, 20 * i, axis=1))
    write_rgb(calib / "000000.depth.png", np.zeros(IMAGE_HW, np.uint16))  # skipped
    assert len(calibration_images(calib)) == 4

    fp32 = export_checkpoint(fitted, tmp_path / "fp32.onnx")
    res = export_checkpoint(fitted, tmp_path / "int8.onnx", int8=Int8Calibration(calib))
    assert res.info.precision == "int8" and res.int8 is not None
    dev = res.int8
    assert dev.images == 4 and dev.instances_ref >= 2
    assert dev.keypoints_compared >= 16 and dev.median_px < 1.0
    assert dev.belief_max_abs < 0.1 and dev.mean_abs < 0.01
    proto = onnx.load(str(tmp_path / "int8.onnx"))
    ops = {n.op_type for n in proto.graph.node}
    assert {"QuantizeLinear", "DequantizeLinear"} <= ops  # QDQ format
    assert res.size_bytes < 0.5 * fp32.size_bytes  # int8 weights
    q = json.loads({p.key: p.value for p in proto.metadata_props}["dope_hope.quantization"])
    assert q["per_channel"] and q["format"] == "QDQ" and q["calibration_images"] == 4
    # The measured drift travels in the file; loading it says what INT8 costs.
    assert q["drift"]["median_px"] == pytest.approx(dev.median_px)
    from dope_hope.inference.onnx_backend import OnnxBackend

    said = OnnxBackend(tmp_path / "int8.onnx").describe()
    assert said.startswith("int8.onnx: ONNX INT8, keypoints vs fp32 at export: median ")
    assert f"over {dev.keypoints_compared} keypoints of 4 images" in said
    assert OnnxBackend(tmp_path / "fp32.onnx").describe() == "fp32.onnx: ONNX fp32"
    # The maps come out of a float conv (no 1/255-of-range output quantization step).
    assert _ops_to_last_conv(proto, "belief") == ["Slice", "Conv"]
    # isaac-ros too: concat + channel gather stay float.
    isaac = export_checkpoint(fitted, tmp_path / "isaac8.onnx",
                              ExportSettings(layout="isaac-ros", input_hw=(IMAGE_HW[0], IMAGE_HW[1])),
                              Int8Calibration(calib, count=2))
    assert isaac.int8.median_px < 1.0
    assert _ops_to_last_conv(onnx.load(str(tmp_path / "isaac8.onnx")), "output") == ["Gather", "Concat", "Slice", "Conv"]


def _ops_to_last_conv(proto, output: str) -> list[str]:
    """Op types from a graph output back to the first Conv (first inputs followed)."""
    producer = {o: n for n in proto.graph.node for o in n.output}
    ops, node = [], producer[output]
    while True:
        ops.append(node.op_type)
        if node.op_type == "Conv":
            return ops
        node = producer[node.input[0]]


def test_compare_maps_measures_keypoint_shift():
    _, kp = scene()
    ref = make_targets(kp[None], IMAGE_HW, 8, sigma=1.0, radius=1.0)
    shifted = make_targets(kp[None] + [2.0, 0.0], IMAGE_HW, 8, sigma=1.0, radius=1.0)
    dev = compare_maps([ref], [shifted], stride=8)
    assert dev.instances_matched == 1 and dev.keypoints_compared == 9
    assert dev.median_px == pytest.approx(2.0, abs=0.05)
    assert dev.peaks_ref == dev.peaks_matched == 9 and dev.peak_median_px == pytest.approx(2.0, abs=0.05)
    same = compare_maps([ref], [ref], stride=8)
    assert same.max_abs == 0 and same.max_px == 0


def test_cli_export_and_one_line_errors(fitted, tmp_path, capsys):
    out = tmp_path / "cli.onnx"
    assert main(["export", "--weights", str(fitted), "--out", str(out), "--layout", "isaac-ros",
                 "--height", "96", "--width", "128", "--isaac-ros-version", "3.1"]) == 0
    text = capsys.readouterr().out
    assert "Isaac ROS 3.1: isaac_ros_dope_tensor_rt.launch.py arguments" in text
    for arg in ("network_image_width:=128", "network_image_height:=96", "encoder_image_mean:='[0.5, 0.5, 0.5]'",
                f"model_file_path:={out.resolve()}", "object_name:=Ketchup", "input_image_width:=1920",
                "input_binding_names:='[\"input\"]'", "output_binding_names:='[\"output\"]'"):
        assert arg in text, arg
    assert '"Ketchup": [6.4514, 14.8608, 4.3368]' in text and "mesh-frame pose" in text
    assert "replaces the stock entry" in text and "your camera's image size" in text
    assert OnnxBackend(out).layout == "isaac-ros"
    # The current release: its core launch file's arguments, ImageNet encoder by default.
    assert main(["export", "--weights", str(fitted), "--out", str(out), "--layout", "isaac-ros",
                 "--height", "96", "--width", "128", "--json"]) == 0
    isaac = json.loads(capsys.readouterr().out)["isaac_ros"]
    assert isaac["version"] == ISAAC_ROS_CURRENT and isaac["launch_file"] == "isaac_ros_dope_core.launch.py"
    args = isaac["launch_arguments"]
    assert args["encoder_image_mean"] == "[0.485, 0.456, 0.406]" and args["map_peak_threshold"] == "0.1"
    assert args["network_image_width"] == "128" and "network_image_width" in isaac["changed"]
    assert isaac["channel_order"] == [2, 3, 0, 1, 6, 7, 4, 5, 8]

    bad = [
        (["--height", "100", "--width", "128"], "multiples of 8"),
        (["--height", "96"], "both --height and --width"),
        (["--dynamic", "--height", "96", "--width", "128"], "exclude each other"),
        (["--int8"], "--calibration"),
        (["--int8", "--calibration", str(tmp_path / "none")], "calibration folder not found"),
        (["--opset", "9"], "opset"),
        (["--layout", "isaac-ros", "--isaac-ros-version", "1.1"], "--isaac-ros-version 1.1"),
    ]
    for extra, message in bad:
        assert main(["export", "--weights", str(fitted), "--out", str(tmp_path / "b.onnx")] + extra) == 2
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1, err
    assert main(["export", "--weights", str(tmp_path / "missing.pt"), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "missing.pt" in err and err.count("\n") == 1
    assert not (tmp_path / "b.onnx").exists()


def test_export_refuses_an_onnx_input(tmp_path):
    (tmp_path / "m.onnx").write_bytes(b"x")
    with pytest.raises(InputFileError, match="already an ONNX model"):
        export_checkpoint(tmp_path / "m.onnx", tmp_path / "o.onnx")


def test_checkpoint_round_trip_through_export(tmp_path):
    cfg = _lite_config()
    model = build_model(cfg)
    save_checkpoint(tmp_path / "c.pt", model, cfg, {"class_name": "Mustard"})
    res = export_checkpoint(tmp_path / "c.pt", tmp_path / "c.onnx", ExportSettings(dynamic=True))
    assert res.info.class_name == "Mustard" and res.info.source == "c.pt" and res.verify_max_abs < TOL


def test_cpu_int8_support_reads_the_instruction_set():
    from dope_hope.export.int8 import cpu_int8_support

    assert cpu_int8_support("flags\t: fpu sse2 avx avx2 fma", "x86_64") == (False, "x86-64 AVX2, no VNNI")
    assert cpu_int8_support("flags\t: avx2 avx512f avx512_vnni", "x86_64") == (
        True, "x86-64 AVX-512 with AVX512_VNNI")
    assert cpu_int8_support("flags\t: avx2 avx_vnni", "x86_64")[0] is True
    assert cpu_int8_support("Features\t: fp asimd asimddp", "aarch64") == (True, "ARM64 with the dot-product extension")
    assert cpu_int8_support("Features\t: fp asimd", "aarch64")[0] is False
    assert cpu_int8_support("", "riscv64")[0] is None
