"""Checkpoints: round trip, atomic writes, weights_only safety, bad files, official import."""
from __future__ import annotations

import errno

import numpy as np
import pytest
import torch

from dope_hope.catalog import get_object
from dope_hope.config import load_config
from dope_hope.errors import ModelFileError, OutputPathError, UnknownObjectError
from dope_hope.geometry import KEYPOINT_ORDER, LEGACY_KEYPOINT_ORDER
from dope_hope.model import IMAGENET_MEAN, IMAGENET_STD, build_model
from dope_hope.model.checkpoint import (
    TrainingState,
    import_official,
    load_checkpoint,
    load_model,
    make_object_info,
    restore_rng_state,
    save_checkpoint,
    save_inference_checkpoint,
)
from dope_hope.model.settings import ModelSettings

torch.set_num_threads(1)

LITE = {"model": {"arch": "lite", "head": 50, "stages": 2,
                  "lite": {"width": 8, "feature_channels": 16, "stage_channels": 16}},
        "input": {"size": [64, 64]}}


class NotAWeight:
    """A custom class: weights_only loading must refuse to unpickle it."""

    def __reduce__(self):
        return (print, ("this must never run",))


def _trained_lite():
    model = build_model(LITE)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-3)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=10)
    out = model(torch.randn(2, 3, 64, 64))
    sum((b ** 2).mean() + (a ** 2).mean() for b, a in out).backward()
    opt.step()
    sched.step()
    return model, opt, sched


def test_round_trip_restores_weights_optimizer_and_rng(tmp_path):
    model, opt, sched = _trained_lite()
    path = tmp_path / "run" / "last.pth"
    save_checkpoint(path, model, LITE, make_object_info("Ketchup"),
                    TrainingState(opt, sched, step=7, epoch=2, extra={"best_loss": np.float32(0.25)}))
    expected_draws = (np.random.rand(), torch.rand(3))
    ckpt = load_checkpoint(path)
    restore_rng_state(ckpt["rng"])  # resume draws the same random numbers
    assert np.random.rand() == expected_draws[0]
    assert torch.equal(torch.rand(3), expected_draws[1])

    assert ckpt["step"] == 7 and ckpt["epoch"] == 2 and ckpt["extra"] == {"best_loss": 0.25}
    assert ckpt["config"] == LITE
    assert ckpt["object"] == {"class_name": "Ketchup",
                              "size_m": list(get_object("Ketchup").size), "frame": "mesh"}
    assert ckpt["keypoint_order"] == KEYPOINT_ORDER
    assert ckpt["normalization"] == {"mean": list(IMAGENET_MEAN), "std": list(IMAGENET_STD)}
    loaded, ckpt2 = load_model(path)
    assert not loaded.training
    for key, value in model.state_dict().items():
        assert torch.equal(loaded.state_dict()[key], value), key
    opt2 = torch.optim.AdamW(loaded.parameters(), lr=1e-3)
    opt2.load_state_dict(ckpt2["optimizer"])
    state, state2 = opt.state_dict()["state"], opt2.state_dict()["state"]
    assert torch.equal(state[0]["exp_avg"], state2[0]["exp_avg"])
    sched2 = torch.optim.lr_scheduler.CosineAnnealingLR(opt2, T_max=10)
    sched2.load_state_dict(ckpt2["scheduler"])
    assert sched2.last_epoch == 1


def test_inference_checkpoint_drops_training_state_and_keeps_the_model(tmp_path):
    model, opt, sched = _trained_lite()
    full = save_checkpoint(tmp_path / "last.pt", model, LITE, make_object_info("Ketchup"),
                           TrainingState(opt, sched, step=3))
    slim = save_inference_checkpoint(full, tmp_path / "ship.pt")
    assert slim.stat().st_size < 0.6 * full.stat().st_size  # Adam's two moments are gone
    loaded, ckpt = load_model(slim)
    assert ckpt["optimizer"] is None and ckpt["scheduler"] is None and ckpt["rng"] is None
    assert ckpt["object"]["class_name"] == "Ketchup" and ckpt["step"] == 3
    for key, value in model.state_dict().items():
        assert torch.equal(loaded.state_dict()[key], value), key


def test_failed_write_leaves_old_file_and_no_partial(tmp_path, monkeypatch):
    model = build_model(LITE)
    path = tmp_path / "ckpt.pth"
    save_checkpoint(path, model, LITE, make_object_info("Ketchup"), TrainingState(step=1))
    before = path.read_bytes()

    def crashing_save(obj, f, *args, **kwargs):  # half a file, then the disk is full
        f.write(b"PK\x03\x04 half a file")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(torch, "save", crashing_save)
    with pytest.raises(OutputPathError, match="ckpt.pth: cannot write .no space left on device"):
        save_checkpoint(path, model, LITE, make_object_info("Ketchup"), TrainingState(step=2))
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ckpt.pth"]
    with pytest.raises(OutputPathError):
        save_checkpoint(tmp_path / "new.pth", model, LITE, make_object_info("Ketchup"))
    assert not (tmp_path / "new.pth").exists()


def test_pickled_custom_class_is_refused(tmp_path, capsys):
    path = tmp_path / "evil.pth"
    torch.save({"format": "dope-hope-checkpoint", "model": {}, "payload": NotAWeight()}, path)
    with pytest.raises(ModelFileError, match="weights_only") as info:
        load_checkpoint(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)
    assert "must never run" not in capsys.readouterr().out


def test_truncated_and_foreign_files(tmp_path):
    model = build_model(LITE)
    good = tmp_path / "good.pth"
    save_checkpoint(good, model, LITE, make_object_info("Ketchup"))
    data = good.read_bytes()
    cut = tmp_path / "cut.pth"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(ModelFileError, match="truncated") as info:
        load_checkpoint(cut)
    assert str(cut) in str(info.value)
    text = tmp_path / "notes.pth"
    text.write_text("hello")
    with pytest.raises(ModelFileError, match="notes.pth"):
        load_checkpoint(text)
    with pytest.raises(ModelFileError, match="file not found"):
        load_checkpoint(tmp_path / "missing.pth")
    bare = tmp_path / "bare.pth"
    torch.save(model.state_dict(), bare)
    with pytest.raises(ModelFileError, match="bare state dict"):
        load_checkpoint(bare)


def test_weights_for_another_architecture(tmp_path):
    model = build_model(LITE)
    path = tmp_path / "ckpt.pth"
    save_checkpoint(path, model, LITE, make_object_info("Ketchup"))
    ckpt = torch.load(path, weights_only=True)
    ckpt["model"]["m7_1.0.weight"] = torch.zeros(1)
    extra_key = tmp_path / "extra_key.pth"
    torch.save(ckpt, extra_key)
    with pytest.raises(ModelFileError, match=r"unexpected keys m7_1\.0\.weight.*another architecture"):
        load_checkpoint(extra_key)
    # same names, other widths: the config says width 8, the weights are the default lite
    wide = {"model": {"arch": "lite", "head": 50, "stages": 2}}
    ckpt["model"] = build_model(wide).state_dict()
    wrong_shapes = tmp_path / "wrong_shapes.pth"
    torch.save(ckpt, wrong_shapes)
    with pytest.raises(ModelFileError, match="has shape .* another architecture") as info:
        load_model(wrong_shapes)
    assert str(wrong_shapes) in str(info.value)


def test_import_official_records_legacy_frame(tmp_path):
    official = {f"module.{k}": v for k, v in build_model(load_config("dope_dr_50")).state_dict().items()}
    pth = tmp_path / "BBQSauce.pth"
    torch.save(official, pth)
    ckpt = import_official(pth, "BBQSauce")
    assert ckpt["object"]["frame"] == "legacy"
    assert ckpt["keypoint_order"] == LEGACY_KEYPOINT_ORDER
    assert ckpt["object"]["size_m"] == pytest.approx(list(get_object("BBQSauce").size))
    assert ModelSettings.from_mapping(ckpt["config"].get("model")) == ModelSettings(arch="dope", head=50, stages=6)
    assert ckpt["normalization"]["mean"] == list(IMAGENET_MEAN)
    assert ckpt["normalization"]["std"] == list(IMAGENET_STD)
    assert "BBQSauce.pth" in ckpt["source"]
    with pytest.raises(UnknownObjectError):
        import_official(pth, "Banana")
    lite_bare = tmp_path / "lite.pth"
    torch.save(build_model(LITE).state_dict(), lite_bare)
    with pytest.raises(ModelFileError, match="another architecture"):
        import_official(lite_bare, "Ketchup")


def test_checkpoint_does_not_reload_backbone_file(tmp_path):
    """The trunk comes from the checkpoint, not from the (maybe gone) ImageNet file."""
    config = {"model": {"arch": "dope", "head": 50, "stages": 1,
                        "backbone_weights": str(tmp_path / "gone" / "vgg19.pth")}}
    model = build_model({"arch": "dope", "head": 50, "stages": 1})
    path = tmp_path / "ckpt.pth"
    save_checkpoint(path, model, config, make_object_info("Mustard", frame="mesh"))
    loaded, ckpt = load_model(path)
    assert ckpt["config"] == config
    assert torch.equal(loaded.m1_2[8].weight, model.m1_2[8].weight)
