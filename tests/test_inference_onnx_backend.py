"""OnnxBackend: metadata from the file alone, detections equal to PyTorch's, bad files."""
from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import onnx
import pytest
import torch
from fitted_model import CLASS_NAME, IMAGE_HW, K, fit_lite_checkpoint, scene
from onnx import TensorProto, helper

from dope_hope.cli import main
from dope_hope.errors import ConfigError, ModelFileError
from dope_hope.export.pipeline import export_checkpoint
from dope_hope.export.to_onnx import ExportSettings
from dope_hope.inference.backends import TorchBackend
from dope_hope.inference.onnx_backend import OnnxBackend, OnnxModelInfo
from dope_hope.inference.predictor import DopePredictor
from dope_hope.model.checkpoint import save_inference_checkpoint

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    """(checkpoint, native fixed-size .onnx, dynamic .onnx, isaac-ros .onnx) of the fitted model."""
    d = tmp_path_factory.mktemp("onnx")
    ckpt = fit_lite_checkpoint(d / "fitted.pt")
    export_checkpoint(ckpt, d / "native.onnx")
    export_checkpoint(ckpt, d / "dynamic.onnx", ExportSettings(dynamic=True))
    # The current Isaac ROS release (channels in its vertex order) with the 0.5/0.5 encoder.
    export_checkpoint(ckpt, d / "isaac.onnx",
                      ExportSettings(layout="isaac-ros", isaac_encoder="half", input_hw=(IMAGE_HW[0], IMAGE_HW[1])))
    return ckpt, d / "native.onnx", d / "dynamic.onnx", d / "isaac.onnx"


def _assert_same_detections(a, b, px=0.5):
    assert len(a) == len(b) >= 1
    for da, db in zip(a, b):
        present = np.isfinite(da.keypoints_2d[:, 0])
        assert np.array_equal(present, np.isfinite(db.keypoints_2d[:, 0]))
        assert np.abs(da.keypoints_2d[present] - db.keypoints_2d[present]).max() < px
        assert np.abs(da.t - db.t).max() < 0.01 and abs(da.score - db.score) < 0.02


def test_metadata_comes_from_the_file(models):
    ckpt, native, dynamic, _ = models
    torch_b = TorchBackend.load(ckpt)
    b = OnnxBackend(native, threads=1)
    assert b.class_name == CLASS_NAME == torch_b.class_name
    np.testing.assert_allclose(b.size_m, torch_b.size_m)
    assert (b.stride, b.frame, b.keypoint_order) == (8, "mesh", "dope-current")
    assert b.mean == pytest.approx(torch_b.mean) and b.std == pytest.approx(torch_b.std)
    assert b.input_hw == IMAGE_HW and b.fixed_input_hw == IMAGE_HW
    assert b.providers == ["CPUExecutionProvider"] and b.info.precision == "fp32"
    assert OnnxBackend(dynamic).fixed_input_hw is None
    session = b.session
    x = np.zeros((1, 3) + IMAGE_HW, np.float32)
    b.run(x)
    b.run(x)
    assert b.session is session  # built once, reused
    with pytest.raises(ValueError, match="takes 96x128 inputs only"):
        b.run(np.zeros((1, 3, 64, 64), np.float32))


@pytest.mark.parametrize("which", ["native", "dynamic", "isaac"])
def test_detections_match_the_torch_backend(models, which):
    ckpt, native, dynamic, isaac = models
    path = {"native": native, "dynamic": dynamic, "isaac": isaac}[which]
    rgb, kp = scene()
    torch_pred = DopePredictor(ckpt, threads=1)
    onnx_pred = DopePredictor(path, backend="onnx", threads=1)
    assert isinstance(onnx_pred.backend, OnnxBackend)

    tb, ta, net_in = torch_pred.infer_maps(rgb)
    ob, oa, _ = onnx_pred.infer_maps(net_in)
    assert np.abs(tb - ob).max() < 1e-4 and np.abs(ta - oa).max() < 1e-4

    ref = torch_pred.predict(rgb, K)
    _assert_same_detections(ref, onnx_pred.predict(rgb, K))
    assert np.abs(ref[0].keypoints_2d - kp).max() < 1.0  # and they find the box
    # An image of another size goes through the same resize path in both backends.
    big = cv2.resize(rgb, (IMAGE_HW[1] * 2, IMAGE_HW[0] * 2), interpolation=cv2.INTER_LINEAR)
    K2 = K.copy()
    K2[:2] *= 2
    K2[:2, 2] += 0.5
    _assert_same_detections(torch_pred.predict(big, K2), onnx_pred.predict(big, K2))


def test_isaac_ros_file_runs_batches_and_converts_normalization(models):
    _, native, _, isaac = models
    n, i = OnnxBackend(native), OnnxBackend(isaac)
    assert i.layout == "isaac-ros" and i.info.input_mean == (0.5, 0.5, 0.5)
    x = np.random.default_rng(0).standard_normal((2, 3) + IMAGE_HW).astype(np.float32)
    for got, ref in zip(i.run(x), n.run(x)):
        assert got.shape == ref.shape and np.abs(got - ref).max() < 1e-4
    feed = i.feeds(x)
    assert len(feed) == 2 and feed[0]["input"].shape == (1, 3) + IMAGE_HW


def test_unusable_files_give_one_line_errors(models, tmp_path, capsys):
    _, native, _, isaac = models
    image = tmp_path / "img.png"
    cv2.imwrite(str(image), scene()[0])
    data = native.read_bytes()
    cases = {}
    (tmp_path / "truncated.onnx").write_bytes(data[: len(data) // 2])
    cases["truncated.onnx"] = "truncated or corrupt"
    (tmp_path / "random.onnx").write_bytes(np.random.default_rng(0).bytes(4096))
    cases["random.onnx"] = "truncated or corrupt"
    x = helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 3, 8, 8])
    y = helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 3, 8, 8])
    foreign = helper.make_model(helper.make_graph([helper.make_node("Relu", ["x"], ["y"])], "g", [x], [y]),
                                opset_imports=[helper.make_opsetid("", 17)])
    foreign.ir_version = 99
    onnx.save(foreign, str(tmp_path / "future.onnx"))
    cases["future.onnx"] = "onnxruntime cannot load it: Unsupported model IR version: 99"
    foreign.ir_version = 8
    onnx.save(foreign, str(tmp_path / "foreign.onnx"))
    cases["foreign.onnx"] = "not a dope-hope model: inputs ['x'], outputs ['y']"
    stripped = onnx.load(str(native))
    del stripped.metadata_props[:]
    onnx.save(stripped, str(tmp_path / "no_metadata.onnx"))
    cases["no_metadata.onnx"] = "without dope-hope metadata"
    tampered = onnx.load(str(native))
    for p in tampered.metadata_props:
        if p.key == "dope_hope.size_m":
            p.value = "[0.1, 0.2]"
    onnx.save(tampered, str(tmp_path / "tampered.onnx"))
    cases["tampered.onnx"] = "size_m must hold 3 finite numbers"
    reordered = onnx.load(str(isaac))
    for p in reordered.metadata_props:
        if p.key == "dope_hope.isaac_ros.channel_order":
            p.value = "[0, 0, 1, 2, 3, 4, 5, 6, 8]"
    onnx.save(reordered, str(tmp_path / "reordered.onnx"))
    cases["reordered.onnx"] = "isaac_ros.channel_order: not a permutation"
    threshold = onnx.load(str(native))
    threshold.metadata_props.add(key="dope_hope.min_score", value="nan")
    onnx.save(threshold, str(tmp_path / "threshold.onnx"))
    cases["threshold.onnx"] = "min_score must be a finite number >= 0 or null, got nan"
    cases["missing.onnx"] = "not found"
    for name, problem in cases.items():
        with pytest.raises(ModelFileError) as err:
            OnnxBackend(tmp_path / name)
        msg = str(err.value)
        assert msg.startswith(str(tmp_path / name)) and problem in msg and "\n" not in msg, msg
        # and through the CLI: exit status 2, the same one line
        assert main(["infer", str(image), "--weights", str(tmp_path / name)]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and problem in err and name in err, err


def test_session_options(models):
    _, native, _, _ = models
    with pytest.raises(ConfigError, match="optimization"):
        OnnxBackend(native, optimization="max")
    with pytest.warns(RuntimeWarning, match="not available"):
        b = OnnxBackend(native, providers=["NoSuchExecutionProvider"], optimization="disable")
    assert b.providers == ["CPUExecutionProvider"]
    x = np.zeros((1, 3) + IMAGE_HW, np.float32)
    ref = OnnxBackend(native, optimization="all").run(x)
    for got, r in zip(b.run(x), ref):
        assert np.abs(got - r).max() < 1e-4


def test_model_info_round_trip():
    info = OnnxModelInfo(class_name="Mustard", size_m=(0.1, 0.2, 0.05), frame="legacy",
                         keypoint_order="dope-legacy", mean=(0.485, 0.456, 0.406), std=(0.229, 0.224, 0.225),
                         input_mean=(0.5,) * 3, input_std=(0.5,) * 3, stride=8, head=50, arch="dope",
                         layout="isaac-ros", input_hw=None, fixed_input_hw=(480, 640), opset=17,
                         extra={"isaac_ros.encoder": "half"})
    meta = info.to_metadata()
    assert all(isinstance(v, str) for v in meta.values())
    assert json.loads(meta["dope_hope.input_hw"]) is None
    assert "dope_hope.min_score" not in meta  # no threshold of its own: no key
    back = OnnxModelInfo.from_metadata(meta, "x.onnx")
    assert back == info and back.min_score is None
    info.min_score = 0.6
    assert OnnxModelInfo.from_metadata(info.to_metadata(), "x.onnx") == info


def test_a_threshold_recorded_with_the_model_is_its_default(models, tmp_path, capsys):
    """A model's own min_score (its checkpoint, carried into its ONNX export) replaces the
    packaged default; an explicit min_score, in Python or on the command line, still wins."""
    ckpt = models[0]
    rgb, _ = scene()
    (score,) = [d.score for d in DopePredictor(ckpt, min_score=0.0).predict(rgb, K)]
    assert DopePredictor(ckpt).options.min_score == 0.5  # none recorded: the packaged default
    own = save_inference_checkpoint(ckpt, tmp_path / "own.pt", min_score=score + 0.01)
    export_checkpoint(own, tmp_path / "own.onnx")
    assert OnnxBackend(tmp_path / "own.onnx").info.min_score == pytest.approx(score + 0.01)
    for weights in (own, tmp_path / "own.onnx"):
        assert DopePredictor(weights).options.min_score == pytest.approx(score + 0.01)
        assert DopePredictor(weights).predict(rgb, K) == []
        assert len(DopePredictor(weights, min_score=score - 0.01).predict(rgb, K)) == 1
    cv2.imwrite(str(tmp_path / "image.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    cmd = ["infer", str(tmp_path / "image.png"), "--weights", str(own), "--fx", str(fx), "--fy", str(fy),
           "--cx", str(cx), "--cy", str(cy), "--no-overlay", "--out", str(tmp_path / "res")]
    for extra, found in (([], 0), (["--min-score", "0"], 1)):
        assert main(cmd + extra) == 0
        captured = capsys.readouterr()
        assert sum(line.startswith("{") for line in captured.out.splitlines()) == found
        assert ("the model's own" in captured.err) == (not extra), captured.err
    with pytest.raises(ModelFileError, match="min_score must be a finite number >= 0 or null"):
        save_inference_checkpoint(ckpt, tmp_path / "bad.pt", min_score=-0.1)
    assert not (tmp_path / "bad.pt").exists()


def test_cli_infer_needs_only_the_onnx_file(models, tmp_path, capsys):
    _, native, _, _ = models
    alone = tmp_path / "alone"
    alone.mkdir()
    shutil.copy(native, alone / "model.onnx")  # no checkpoint anywhere near it
    rgb, kp = scene()
    cv2.imwrite(str(alone / "image.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    code = main(["infer", str(alone / "image.png"), "--weights", str(alone / "model.onnx"),
                 "--fx", str(fx), "--fy", str(fy), "--cx", str(cx), "--cy", str(cy),
                 "--out", str(tmp_path / "res"), "--no-overlay"])
    out = capsys.readouterr().out
    assert code == 0
    records = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
    assert len(records) == 1 and records[0]["class"] == CLASS_NAME
    assert np.abs(np.array(records[0]["keypoints_2d"], dtype=float) - kp).max() < 1.0
