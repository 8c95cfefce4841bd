"""ONNX export: graphs reproduce PyTorch, metadata, Isaac ROS layout, INT8, CLI, bad options."""
from __future__ import annotations

import json

import numpy as np
import onnx
import pytest
import torch
from fitted_model import IMAGE_HW, fit_lite_checkpoint, scene

from dope_hope.cli import main
from dope_hope.config import load_config
from dope_hope.errors import ConfigError, InputFileError
from dope_hope.export.compare import compare_maps
from dope_hope.export.int8 import list_images
from dope_hope.export.pipeline import export_checkpoint
from dope_hope.export.to_onnx import ISAAC_ENCODERS, export_model
from dope_hope.inference.onnx_backend import OnnxBackend
from dope_hope.io.images import write_rgb
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

    export_model(model, ckpt, tmp_path / "dyn.onnx", dynamic=True)
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
    export_model(model, ckpt, path, input_hw=(48, 72), opset=17, source="lite.pt")
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
    info, _ = export_model(model, ckpt, path, layout="isaac-ros")
    assert info.fixed_input_hw == (480, 640)  # Isaac ROS DOPE's default network size
    proto = onnx.load(str(path))
    dims = lambda v: [d.dim_value for d in v.type.tensor_type.shape.dim]  # noqa: E731
    assert [(i.name, dims(i)) for i in proto.graph.input] == [("input", [1, 3, 480, 640])]
    assert [(o.name, dims(o)) for o in proto.graph.output] == [("output", [1, 25, 60, 80])]
    meta = {p.key: p.value for p in proto.metadata_props}
    assert json.loads(meta["dope_hope.input_mean"]) == [0.5, 0.5, 0.5]
    assert json.loads(meta["dope_hope.isaac_ros.object_dimensions_cm"]) == pytest.approx(
        [6.4514, 14.8608, 4.3368])

    # Fed a 0.5/0.5-normalized image, the graph reproduces the native maps.
    import onnxruntime as ort

    rgb = np.random.default_rng(2).random((1, 3, 480, 640), dtype=np.float32)
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    (out,) = sess.run(None, {"input": (rgb - 0.5) / 0.5})
    mean, std = np.array(IMAGENET_MEAN, np.float32), np.array(IMAGENET_STD, np.float32)
    b, a = _torch_maps(model, ((rgb - mean[:, None, None]) / std[:, None, None]).astype(np.float32))
    assert np.abs(out[:, :9] - b).max() < TOL and np.abs(out[:, 9:] - a).max() < TOL

    # ImageNet encoder variant (isaac_ros_dope_core.launch.py default): identity conversion.
    info, _ = export_model(model, ckpt, tmp_path / "isaac_in.onnx", layout="isaac-ros",
                           input_hw=(64, 64), isaac_encoder="imagenet")
    assert info.input_mean == ISAAC_ENCODERS["imagenet"][0]


def test_isaac_ros_refuses_maps_not_at_one_eighth_and_dynamic(tmp_path):
    cfg = _lite_config(head=100)  # stride 4 maps: Isaac ROS DOPE's decoder hard-codes x8
    model = build_model(cfg).eval()
    with pytest.raises(ConfigError, match="stride 4"):
        export_model(model, _ckpt(cfg), tmp_path / "x.onnx", layout="isaac-ros")
    with pytest.raises(ConfigError, match="fixed input size"):
        export_model(build_model(_lite_config()).eval(), _ckpt(_lite_config()), tmp_path / "y.onnx",
                     layout="isaac-ros", dynamic=True)
    assert not list(tmp_path.iterdir())  # nothing written


def test_dope_dr_50_export_matches_pytorch(tmp_path):
    torch.manual_seed(0)
    cfg = load_config("dope_dr_50")
    model = build_model(cfg).eval()
    info, verify = export_model(model, _ckpt(cfg, frame="legacy"), tmp_path / "dr50.onnx",
                                input_hw=(64, 64))
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
    assert len(list_images(calib)) == 4

    fp32 = export_checkpoint(fitted, tmp_path / "fp32.onnx")
    res = export_checkpoint(fitted, tmp_path / "int8.onnx", int8=True, calibration=calib)
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
    # The maps come out of a float conv (no 1/255-of-range output quantization step).
    producer = {o: n for n in proto.graph.node for o in n.output}
    conv = producer[producer["belief"].input[0]]
    assert conv.op_type == "Conv" and q["float_nodes"] == [conv.name]


def test_compare_maps_measures_keypoint_shift():
    from dope_hope.maps.targets import make_targets

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
                 "--height", "96", "--width", "128"]) == 0
    text = capsys.readouterr().out
    assert "isaac-ros" in text and "encoder_image_mean:='[0.5, 0.5, 0.5]'" in text
    assert OnnxBackend(out).layout == "isaac-ros"

    bad = [
        (["--height", "100", "--width", "128"], "multiples of 8"),
        (["--height", "96"], "both --height and --width"),
        (["--dynamic", "--height", "96", "--width", "128"], "exclude each other"),
        (["--int8"], "--calibration"),
        (["--int8", "--calibration", str(tmp_path / "none")], "calibration folder not found"),
        (["--opset", "9"], "opset"),
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
    res = export_checkpoint(tmp_path / "c.pt", tmp_path / "c.onnx", dynamic=True)
    assert res.info.class_name == "Mustard" and res.info.source == "c.pt" and res.verify_max_abs < TOL
