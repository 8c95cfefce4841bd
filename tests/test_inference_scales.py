"""Several working sizes of a trained model (``multiscale.scales``): an object the network
misses at its working size and finds at another is detected, placed by -LS after the
pooling; one size given twice is that size; duplicates of one object are pooled by their 2D
boxes, per class; a fixed-size export and the new objects' detector refuse the setting."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from _targets_backend import TargetsBackend, demo_box_frame

from dope_hope import cli
from dope_hope.assets import DEMO_WEIGHTS
from dope_hope.demo_object import DEMO_SIZE_M
from dope_hope.errors import ConfigError
from dope_hope.geometry import rotation_error_deg
from dope_hope.inference.predictor import DopePredictor
from dope_hope.inference.scales import pool_detections, scaled_height
from dope_hope.io.dope_json import read_dope_json
from dope_hope.io.images import read_depth_m, read_rgb


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A 160x120 frame of the demo box, with depth: (frame folder, mesh path, GT R, GT t)."""
    return demo_box_frame(tmp_path_factory.mktemp("scales"))


class BlindAtOneSize(TargetsBackend):
    """Perfect maps of the scene, except at a working height of ``blind_height`` px: none."""

    blind_height: int | None = None

    def run(self, batch):
        belief, affinity = super().run(batch)
        if self.calls[-1]["resized"][0] == self.blind_height:
            return np.zeros_like(belief), np.zeros_like(affinity)
        return belief, affinity


def predict(scene, backend, distance_factor=1.0, **options):
    """(predictor, detections with -LS) of ``backend`` on the frame; the model's box at
    ``distance_factor`` times the true distance (-LS brings it back)."""
    frame_dir, demo, R, t = scene
    frame = read_dope_json(frame_dir / "000000.json")
    backend.poses = [(R, t * distance_factor)]
    p = DopePredictor(backend, mesh=demo, options=options)
    return p, p.predict(read_rgb(frame_dir / "000000.png"), frame.K, depth=read_depth_m(frame_dir / "000000.depth.png"))


def backend_of(scene, cls=TargetsBackend):
    frame = read_dope_json(scene[0] / "000000.json")
    return cls("DemoBox", DEMO_SIZE_M, [], frame.K, (frame.height, frame.width))


def test_another_size_finds_what_the_working_size_misses(scene):
    _, _, R_gt, t_gt = scene
    backend = backend_of(scene, BlindAtOneSize)
    p, _ = predict(scene, backend)
    base = p.working_size((120, 160))[0][0]
    backend.blind_height = base
    assert predict(scene, backend)[1] == []  # one size: the network sees nothing there
    backend.calls.clear()
    p, (det,) = predict(scene, backend, distance_factor=1.1, multiscale={"scales": [1.0, 0.5]})
    assert [c["resized"][0] for c in backend.calls] == [base, scaled_height(base, 0.5)]
    assert rotation_error_deg(det.R, R_gt) < 1.0
    assert det.ls_applied and np.linalg.norm(det.t - t_gt) < 0.01  # -LS ran on the pooled detection
    box = det.bbox_2d  # of the pose -LS placed, not the keypoints' 10 % farther one
    _, (plain,) = predict(scene, backend_of(scene))
    np.testing.assert_allclose(box, plain.bbox_2d, atol=1.0)


def test_the_gate_runs_the_other_sizes_only_where_the_first_leaves_belief_unexplained(scene):
    """multiscale.gate: where the working size finds the box (all belief inside its 2D box)
    the other size does not run and the detection is the one-size one; where the working size
    sees belief but finds no box (a partly hidden one: its maps too weak to decode), the other
    size runs and finds it."""
    _, _, R_gt, _ = scene
    backend = backend_of(scene)
    _, (one,) = predict(scene, backend)
    base = backend.calls[-1]["resized"][0]
    backend.calls.clear()
    _, (gated,) = predict(scene, backend, multiscale={"scales": [1.0, 0.5], "gate": 0.1})
    assert [c["resized"][0] for c in backend.calls] == [base]
    for field in ("R", "t", "bbox_2d"):
        np.testing.assert_array_equal(getattr(one, field), getattr(gated, field), err_msg=field)

    class FaintAtOneSize(BlindAtOneSize):  # the working size's maps at a fifth: below decoding
        def run(self, batch):
            belief, affinity = TargetsBackend.run(self, batch)
            return (0.2 * belief, affinity) if self.calls[-1]["resized"][0] == self.blind_height else (belief, affinity)

    faint = backend_of(scene, FaintAtOneSize)
    faint.blind_height = base
    assert predict(scene, faint, min_score=0.5)[1] == []
    faint.calls.clear()
    _, (found,) = predict(scene, faint, min_score=0.5, multiscale={"scales": [1.0, 0.5], "gate": 0.1})
    assert [c["resized"][0] for c in faint.calls] == [base, scaled_height(base, 0.5)]
    assert rotation_error_deg(found.R, R_gt) < 1.0
    faint.calls.clear()
    assert predict(scene, faint, min_score=0.5, multiscale={"scales": [1.0, 0.5], "gate": 0.5})[1] == []
    assert len(faint.calls) == 1  # the faint belief stays under a gate of 0.5: one size


def test_one_size_twice_is_that_size(scene):
    """The same size twice: every detection pooled with its own copy, the depth stages after
    the pooling place it exactly as they do at one size."""
    _, (one,) = predict(scene, backend_of(scene), distance_factor=1.1)
    _, (twice,) = predict(scene, backend_of(scene), distance_factor=1.1, multiscale={"scales": [1.0, 1.0]})
    for field in ("R", "t", "keypoints_2d", "projected_2d", "bbox_2d"):
        np.testing.assert_array_equal(getattr(one, field), getattr(twice, field), err_msg=field)
    assert (one.score, one.ls_applied, one.ls_scale, one.ls_reason) == \
        (twice.score, twice.ls_applied, twice.ls_scale, twice.ls_reason)


def _det(name, score, box):
    return SimpleNamespace(class_name=name, score=score, bbox_2d=np.array(box, dtype=float))


def test_duplicates_are_pooled_by_their_boxes_per_class():
    a = _det("Can", 0.6, [0, 0, 10, 10])
    a_again = _det("Can", 0.9, [1, 0, 11, 10])      # IoU 0.82 with a: the same can, higher score
    beside = _det("Can", 0.5, [6, 0, 16, 10])       # IoU 0.25 with a_again: another can
    other = _det("Milk", 0.4, [0, 0, 10, 10])       # the same box, another object
    assert pool_detections([a, a_again, beside, other], 0.5) == [a_again, beside, other]
    assert pool_detections([a, a_again, beside, other], 0.9) == [a_again, a, beside, other]
    assert pool_detections([], 0.5) == []


def test_a_fixed_size_export_and_bad_scales_are_refused(scene, tmp_path, capsys):
    backend = backend_of(scene)
    backend.fixed_input_hw = (120, 160)
    with pytest.raises(ConfigError, match=r"multiscale.scales: this model takes 120x160 inputs only"):
        DopePredictor(backend, multiscale={"scales": [1.0, 0.75]})
    assert DopePredictor(backend, multiscale={"scales": [1.0]}).options.multiscale.scales == (1.0,)
    frame = scene[0] / "000000.png"
    for value, says in (("[1.0,0]", "> 0"), ("[]", "non-empty list")):
        code = cli.main(["infer", str(frame), "--weights", str(DEMO_WEIGHTS), "--out", str(tmp_path / "o"),
                         "--set", f"multiscale.scales={value}"])
        lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
        assert code == 2 and len(lines) == 1 and "multiscale.scales" in lines[0] and says in lines[0], lines
    assert not (tmp_path / "o").exists()
