"""Evaluation: matching rules, BOP19 scoring rules, and `dope-hope evaluate` end to end."""
from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dope_hope.annotation import FrameAnnotation, ObjectAnnotation
from dope_hope.catalog import get_object
from dope_hope.cli import main
from dope_hope.errors import ConfigError, InputFileError, UnknownObjectError
from dope_hope.evaluation import metrics
from dope_hope.evaluation.bop19 import (
    BOP19_MSSD_THRESHOLDS,
    BopTarget,
    bop_mspd_error,
    bop_mssd_error,
    bop_recalls,
    target_matches,
)
from dope_hope.evaluation.datasets import load_dataset
from dope_hope.evaluation.evaluate import (
    EvalConfig,
    cuboid_centres_to_origins,
    run_evaluation,
)
from dope_hope.evaluation.matching import greedy_match
from dope_hope.evaluation.object_models import ObjectModel, load_models
from dope_hope.io.dope_json import write_dope_json
from dope_hope.io.images import write_depth_mm, write_rgb
from dope_hope.io.predictions import prediction_record, write_predictions_jsonl

K = np.array([[60.0, 0.0, 39.5], [0.0, 60.0, 29.5], [0.0, 0.0, 1.0]])
W, H = 80, 60


def rot(axis: str, deg: float) -> np.ndarray:
    return Rotation.from_euler(axis, deg, degrees=True).as_matrix()


# ----------------------------------------------------------------------------- matching
def test_greedy_match_takes_estimates_by_descending_score_and_the_least_error_gt():
    errors = np.array([[1.5, 9.0],    # low score: only close to GT 0
                       [1.0, 2.0]])   # high score: closest to GT 0, also close to GT 1
    m = greedy_match(errors, np.array([0.2, 0.9]), threshold=3.0)
    # the high-scoring estimate takes GT 0; the other one finds GT 1 too far -> unmatched
    assert m.tolist() == [-1, 0]
    # with scores swapped, the first estimate takes GT 0 and the second falls back on GT 1
    assert greedy_match(errors, np.array([0.9, 0.2]), threshold=3.0).tolist() == [0, 1]


def test_greedy_match_threshold_is_strict_and_matching_one_to_one():
    assert greedy_match(np.array([[2.0]]), np.array([1.0]), 2.0).tolist() == [-1]
    assert greedy_match(np.array([[2.0]]), np.array([1.0]), 2.0 + 1e-9).tolist() == [0]
    both = greedy_match(np.array([[0.0], [0.0]]), np.array([0.5, 0.6]), 1.0)
    assert both.tolist() == [-1, 0]
    assert greedy_match(np.zeros((2, 0)), np.ones(2), 1.0).tolist() == [-1, -1]


# ----------------------------------------------------------------------------- BOP rules
def target(errors, scores, vis=None, inst_count=1, kind="mssd"):
    errors = np.asarray(errors, dtype=float)
    vis = np.ones(errors.shape[1]) if vis is None else np.asarray(vis, dtype=float)
    return BopTarget(inst_count, np.asarray(scores, dtype=float), vis, {kind: errors})


def test_bop_rule_correct_only_strictly_below_the_threshold():
    rec = bop_recalls([target([[0.1]], [1.0])], "mssd", [0.1, 0.15])
    assert rec.tolist() == [0.0, 1.0]


def test_bop_rule_only_the_top_inst_count_estimates_are_evaluated():
    # the best-scoring estimate is wrong, the second one is perfect: inst_count = 1 -> missed
    t = target([[0.5], [0.0]], [0.9, 0.5], inst_count=1)
    assert bop_recalls([t], "mssd", [0.2]).tolist() == [0.0]
    t2 = target([[0.5], [0.0]], [0.9, 0.5], vis=[1.0], inst_count=2)  # 2 evaluated, 1 GT
    assert bop_recalls([t2], "mssd", [0.2]).tolist() == [1.0]


def test_bop_rule_one_to_one_matching():
    # two perfect estimates of the same GT, the other GT far away: one true positive of two
    t = target([[0.0, 1.0], [0.0, 1.0]], [0.9, 0.8], inst_count=2)
    assert bop_recalls([t], "mssd", [0.2]).tolist() == [0.5]


def test_bop_rule_only_the_inst_count_most_visible_gt_are_valid():
    # the estimate matches the less visible GT; only the most visible one is a target
    t = target([[0.0, 1.0]], [0.9], vis=[0.2, 0.9], inst_count=1)
    assert bop_recalls([t], "mssd", [0.2]).tolist() == [0.0]


def test_bop_rule_equal_errors_go_to_the_lower_gt_id_and_matching_is_redone_per_threshold():
    """pose_matching.match_poses: estimates by score, each takes the valid unmatched GT whose
    error is strictly below the best so far (initially the threshold), so equal errors keep
    the lower gt_id. A (0.9) is 20 px from both GT, B (0.8) 0 px from gt 0 and 40 px from
    gt 1 (the bench's scene 1 image 5). th <= 20: A unmatched, B -> gt 0; 25..40: A -> gt 0
    (not gt 1), so B finds nothing below th; 45, 50: A -> gt 0, B -> gt 1."""
    t = target([[20.0, 20.0], [0.0, 40.0]], [0.9, 0.8], inst_count=2, kind="mspd")
    th = [float(x) for x in np.arange(5, 51, 5)]
    m = target_matches(t, "mspd", th)[0]
    assert m.tolist() == [[-1, 0]] * 4 + [[0, -1]] * 4 + [[0, 1]] * 2
    assert bop_recalls([t], "mspd", th).tolist() == [0.5] * 8 + [1.0] * 2


def test_bop_rule_ties_in_scores_and_visibility_keep_file_order():
    """eval_calc_errors keeps ``sorted(enumerate(ests), key=score, reverse=True)[:inst_count]``
    and eval_calc_scores validates the GT of ``sorted(range(G), key=visib_fract,
    reverse=True)``: both stable, so among equals the earlier row / gt_id wins."""
    # three equal scores, inst_count 2: the third (a perfect estimate) is never evaluated
    t = target([[np.inf, 0.3], [np.inf, np.inf], [0.0, np.inf]], [0.5, 0.5, 0.5], inst_count=2)
    assert target_matches(t, "mssd", [0.5])[0, 0].tolist() == [1, -1, -1]
    assert bop_recalls([t], "mssd", [0.5]).tolist() == [0.5]
    # equally visible GT, inst_count 1: only gt 0 is valid, so a perfect gt 1 estimate misses
    t = target([[1.0, 0.0]], [0.9], vis=[0.7, 0.7], inst_count=1)
    assert target_matches(t, "mssd", [0.5])[0, 0].tolist() == [-1]


def test_bop_recall_pools_targets_and_vsd_has_one_row_per_tau():
    a = target([[0.0]], [1.0])
    b = target([[0.3]], [1.0])
    np.testing.assert_allclose(bop_recalls([a, b], "mssd", [0.1, 0.5]), [0.5, 1.0])
    v = BopTarget(1, np.ones(1), np.ones(1), {"vsd": np.array([[[0.0, 0.4, 1.0]]])})
    rec = bop_recalls([v], "vsd", [0.1, 0.5])
    assert rec.shape == (3, 2)
    assert rec.tolist() == [[1.0, 1.0], [0.0, 1.0], [0.0, 0.0]]


def test_bop_rule_mssd_short_cut_when_translation_error_reaches_the_diameter():
    # a small box far from the model origin: a rotation about the origin plus a 1 m shift
    # puts it exactly onto itself (MSSD 0 with its symmetry), but |t_e - t_g| >= diameter
    o = np.array([0.5, 0.0, 0.0])
    size = np.array([0.04, 0.02, 0.03])
    pts = metrics.transform_pts(np.random.default_rng(0).uniform(-size / 2, size / 2, (200, 3)),
                                   np.eye(3), o)
    S = np.eye(4)
    S[:3, :3] = rot("z", 180)
    S[:3, 3] = o - rot("z", 180) @ o  # 180° about the box's own z axis
    model = ObjectModel("box", None, "cuboid", pts, float(np.linalg.norm(size)),
                           np.stack([np.eye(4), S]))
    R_g, t_g = np.eye(3), np.array([0.0, 0.0, 2.0])
    R_e, t_e = rot("z", 180), t_g + np.array([1.0, 0.0, 0.0])
    assert metrics.mssd(R_e, t_e, R_g, t_g, pts, model.symmetries) == pytest.approx(0, abs=1e-12)
    assert bop_mssd_error(R_e, t_e, R_g, t_g, model) == math.inf
    # below the diameter the error is the normalized MSSD
    assert bop_mssd_error(R_g, t_g + [0.01, 0, 0], R_g, t_g, model) == pytest.approx(
        0.01 / model.diameter)


def test_bop_mspd_is_scaled_to_width_640():
    model = ObjectModel("box", None, "cuboid", np.array([[0.0, 0, 0], [0.01, 0, 0]]), 0.01,
                           np.eye(4)[None])
    t = np.array([0.0, 0.0, 1.0])
    e = bop_mspd_error(np.eye(3), t + [0.01, 0, 0], np.eye(3), t, K, 1280, model)
    assert e == pytest.approx(60.0 * 0.01 * 640 / 1280)


# ----------------------------------------------------------------------------- end to end
GT = {  # frame -> [(class, R, t, visibility)]
    0: [("Ketchup", rot("y", 30), [-0.15, 0.0, 0.9], 0.9), ("Milk", rot("x", 90), [0.15, 0.0, 1.0], 0.8)],
    1: [("Ketchup", rot("z", 10), [0.0, 0.05, 0.8], 0.7), ("Tuna", np.eye(3), [0.15, 0.0, 0.9], 0.05)],
    2: [("Milk", np.eye(3), [-0.2, 0.0, 1.1], 1.0), ("Milk", rot("y", 90), [0.2, 0.0, 1.1], 0.6)],
}


def write_dataset(folder, with_depth=False):
    folder.mkdir(parents=True, exist_ok=True)
    from dope_hope.render.depth import DepthRenderer

    renderer = DepthRenderer() if with_depth else None
    for k, objs in GT.items():
        anns = [ObjectAnnotation(c, R, np.array(t, dtype=float), visibility=v) for c, R, t, v in objs]
        write_rgb(folder / f"{k:06d}.png", np.zeros((H, W, 3), np.uint8))
        if with_depth:
            depth = np.zeros((H, W))
            for a in anns:
                import trimesh

                box = trimesh.creation.box(extents=get_object(a.class_name).size_array)
                d = renderer.render_depth((box.vertices, box.faces), a.R, a.t, K, W, H)
                depth = np.where((d > 0) & ((depth == 0) | (d < depth)), d, depth)
            write_depth_mm(folder / f"{k:06d}.depth.png", depth)
        write_dope_json(folder / f"{k:06d}.json", FrameAnnotation(folder / f"{k:06d}.json", K, W, H, anns))
    if renderer is not None:
        renderer.close()
    return folder


def shifted(k, i, shift, score=0.9, **kw):
    c, R, t, _ = GT[k][i]
    return prediction_record(f"{k:06d}.png", c, score, R, np.array(t) + np.array(shift), **kw)


def predictions_mixed():
    return [
        shifted(0, 0, [0, 0, 0], ls_applied=True),           # Ketchup perfect
        shifted(0, 1, [0.054, 0, 0], ls_applied=False),      # Milk 5.4 cm
        # frame 1 Ketchup: missing
        shifted(1, 1, [0, 0.012, 0]),                        # Tuna 1.2 cm
        shifted(2, 0, [0, 0, 0], score=0.8),                 # Milk perfect
        shifted(2, 1, [0, 0, 0.033], score=0.3),             # Milk 3.3 cm
        prediction_record("000002", "Ketchup", 0.5, np.eye(3), [0.0, 0.0, 1.0]),  # false positive
    ]


def read_rows(path):
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_end_to_end_recall_precision_table_and_curves(tmp_path, capsys):
    data = write_dataset(tmp_path / "data")
    pred_path = tmp_path / "mixed.jsonl"
    write_predictions_jsonl(pred_path, predictions_mixed(), method="mixed")
    perfect = [shifted(k, i, [0, 0, 0]) for k in GT for i in range(len(GT[k]))]
    perfect_path = tmp_path / "perfect.jsonl"
    write_predictions_jsonl(perfect_path, perfect)
    out = tmp_path / "out"
    rc = main(["evaluate", "--predictions", str(pred_path), str(perfect_path), "--dataset", str(data),
               "--metric", "addh,add", "--out", str(out), "--no-progress"])
    assert rc == 0
    printed = capsys.readouterr().out
    assert "procedural" in printed

    rows = {r["object"]: r for r in read_rows(out / "per_object_mixed.csv")}
    exp = {  # object: (gt, det, P@2, R@2, P@10, R@10, median TP error @10 cm)
        "Ketchup": (2, 2, 0.5, 0.5, 0.5, 0.5, 0.0),
        "Milk": (3, 3, 1 / 3, 1 / 3, 1.0, 1.0, 3.3),
        "Tuna": (1, 1, 1.0, 1.0, 1.0, 1.0, 1.2),
    }
    for name, (gt, det, p2, r2, p10, r10, med) in exp.items():
        r = rows[name]
        assert (int(r["gt"]), int(r["detections"])) == (gt, det)
        got = [float(r[k]) for k in ("precision_2cm", "recall_2cm", "precision_10cm", "recall_10cm",
                                     "median_tp_error_cm")]
        np.testing.assert_allclose(got, [p2, r2, p10, r10, med], atol=1e-9)
    assert rows["Milk"]["category"] == "cuboid" and rows["Tuna"]["category"] == "cylinder"
    assert float(rows["Tuna"]["visibility"]) == pytest.approx(0.05)
    assert float(rows["Milk"]["distance_cm"]) == pytest.approx(100 * np.mean(
        [np.linalg.norm(GT[0][1][2]), 110.0 / 100 * np.sqrt(1 + (0.2 / 1.1) ** 2),
         110.0 / 100 * np.sqrt(1 + (0.2 / 1.1) ** 2)]), rel=1e-9)
    # pixels: silhouette area; the exact silhouette of a box is the hull of its projected corners
    from scipy.spatial import ConvexHull

    from dope_hope.geometry import cuboid_keypoints, project_points

    corners = cuboid_keypoints(get_object("Milk").size_array)[:8]
    exact = np.mean([ConvexHull(project_points(corners, K, R, np.array(t))).volume
                     for c, R, t, _ in GT[0] + GT[2] if c == "Milk"])
    assert float(rows["Milk"]["pixels_area_px2"]) == pytest.approx(exact, rel=0.1)
    means = {r["object"]: r for r in read_rows(out / "per_object_mixed.csv") if r["row"] == "mean"}
    assert set(means) == {"cylinder", "cuboid", "bottle", "overall"}
    assert float(means["overall"]["recall_2cm"]) == pytest.approx((0.5 + 1 / 3 + 1.0) / 3)
    assert float(means["overall"]["recall_10cm"]) == pytest.approx((0.5 + 1.0 + 1.0) / 3)
    perfect_rows = read_rows(out / "per_object_perfect.csv")
    assert all(float(r["recall_2cm"]) == 1.0 and float(r["precision_2cm"]) == 1.0 for r in perfect_rows)

    md = (out / "per_object_mixed.md").read_text()
    for label in ("**cylinder (mean of objects)**", "**cuboid (mean of objects)**",
                  "**bottle (mean of objects)**", "**overall (mean of objects)**", "| Ketchup |"):
        assert label in md
    assert "procedural cuboid" in md and "ADD-H" in md

    curve = [r for r in read_rows(out / "detection_rate.csv")
             if r["method"] == "mixed" and r["metric"] == "addh" and r["group"] == "overall"]
    rate = {float(r["threshold_cm"]): float(r["detection_rate"]) for r in curve}
    assert len(rate) == 20 and min(rate) == 0.5 and max(rate) == 10.0
    expected = {0.5: 2, 1.0: 2, 1.5: 3, 3.0: 3, 3.5: 4, 5.0: 4, 5.5: 5, 10.0: 5}
    for th, n in expected.items():
        assert rate[th] == pytest.approx(n / 6), th
    groups = {r["group"] for r in read_rows(out / "detection_rate.csv")}
    assert {"overall", "cylinder", "cuboid", "bottle", "Ketchup", "Milk", "Tuna"} <= groups
    png = (out / "detection_rate.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 5000
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary["methods"]) == {"mixed", "perfect"}
    assert summary["methods"]["mixed"]["bop19"] is None  # not a BOP dataset, no --bop-ar


def test_min_visible_counts_bop19_targets_only_and_ignores_detections_of_the_others(tmp_path, capsys):
    """Tuna of frame 1 is 5 % visible: with the BOP19 floor it is no GT instance and its
    detection (1.2 cm) neither a true nor a false positive; HOPE's convention (the default)
    counts it."""
    data = write_dataset(tmp_path / "data")
    pred_path = tmp_path / "mixed.jsonl"
    write_predictions_jsonl(pred_path, predictions_mixed(), method="mixed")
    tables = {}
    for floor in ("hope", "bop19", "0.75"):
        out = tmp_path / floor
        assert main(["evaluate", "-p", str(pred_path), "-d", str(data), "--min-visible", floor,
                     "--out", str(out), "--no-progress"]) == 0
        tables[floor] = {r["object"]: r for r in read_rows(out / "per_object_mixed.csv")}
        summary = json.loads((out / "summary.json").read_text())
        assert summary["gt_instances"] == 6
        assert summary["gt_instances_counted"] == {"hope": 6, "bop19": 5, "0.75": 3}[floor]
    assert (tables["hope"]["Tuna"]["gt"], tables["hope"]["Tuna"]["recall_2cm"]) == ("1", "1.0")
    assert tables["bop19"]["Tuna"]["gt"] == "0"
    assert tables["bop19"]["Tuna"]["recall_2cm"] == tables["bop19"]["Tuna"]["precision_2cm"] == ""
    assert tables["bop19"]["Ketchup"] == tables["hope"]["Ketchup"]
    assert float(tables["bop19"]["overall"]["recall_2cm"]) == pytest.approx((0.5 + 1 / 3) / 2)
    # 0.75: Ketchup 0.9 of frame 0 (found), Milk 0.8 (5.4 cm) and 1.0 (found at 0.8); the
    # Milk estimate 3.3 cm off the 0.6-visible Milk is matched to it at 10 cm and not counted
    milk = tables["0.75"]["Milk"]
    assert (milk["gt"], float(milk["recall_2cm"]), float(milk["recall_10cm"])) == ("2", 0.5, 1.0)
    assert float(milk["precision_10cm"]) == 1.0 and float(milk["precision_2cm"]) == pytest.approx(1 / 3)
    assert "GT instances counted: 5 of 6, those at least 0.1 (bop19) visible" in \
        (tmp_path / "bop19" / "per_object_mixed.md").read_text()
    capsys.readouterr()
    assert main(["evaluate", "-p", str(pred_path), "-d", str(data), "--min-visible", "most",
                 "--out", str(tmp_path / "bad"), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--min-visible" in err[0] and "'most'" in err[0]
    assert not (tmp_path / "bad" / "summary.json").exists()


def test_end_to_end_bop_average_recall_without_depth(tmp_path):
    data = write_dataset(tmp_path / "data")
    pred_path = tmp_path / "mixed.jsonl"
    write_predictions_jsonl(pred_path, predictions_mixed())
    s = run_evaluation(EvalConfig(predictions=[pred_path], dataset=data, out=tmp_path / "o",
                                        bop_ar=True), log=lambda _: None)
    bop = s["methods"]["mixed"]["bop19"]
    assert bop["ar_vsd"] is None and any("AR_VSD skipped" in n for n in bop["notes"])
    # targets: visibility >= 0.1 (the 5 %-visible Tuna is not one): 5 GT instances
    assert bop["gt_valid"] == 5
    d_milk = get_object("Milk").diameter
    errs = [0.0, 0.054 / d_milk, 0.0, 0.033 / d_milk]  # MSSD of pure translations / diameter
    expected = [sum(e < th for e in errs) / 5 for th in BOP19_MSSD_THRESHOLDS]
    np.testing.assert_allclose(bop["recalls"]["mssd"], expected)
    assert bop["ar_mssd"] == pytest.approx(np.mean(expected))
    assert bop["ar"] == pytest.approx((bop["ar_mssd"] + bop["ar_mspd"]) / 2)
    md = (tmp_path / "o" / "per_object_mixed.md").read_text()
    assert "BOP19 average recall" in md and "skipped" in md


def test_end_to_end_bop_average_recall_with_depth_perfect_predictions(tmp_path):
    data = write_dataset(tmp_path / "data", with_depth=True)
    perfect = [shifted(k, i, [0, 0, 0]) for k in GT for i in range(len(GT[k]))]
    pred_path = tmp_path / "perfect.jsonl"
    write_predictions_jsonl(pred_path, perfect)
    s = run_evaluation(EvalConfig(predictions=[pred_path], dataset=data, out=tmp_path / "o",
                                        bop_ar=True), log=lambda _: None)
    bop = s["methods"]["perfect"]["bop19"]
    assert bop["ar_vsd"] == pytest.approx(1.0)
    assert bop["ar"] == pytest.approx(1.0)
    # move every estimate 30 cm sideways: nothing is correct any more
    far = [shifted(k, i, [0.3, 0, 0]) for k in GT for i in range(len(GT[k]))]
    write_predictions_jsonl(pred_path, far)
    s = run_evaluation(EvalConfig(predictions=[pred_path], dataset=data, out=tmp_path / "o",
                                        bop_ar=True), log=lambda _: None)
    assert s["methods"]["perfect"]["bop19"]["ar"] == pytest.approx(0.0)


def test_unknown_image_and_ambiguous_mesh_are_user_errors(tmp_path, capsys):
    data = write_dataset(tmp_path / "data")
    bad = tmp_path / "bad.jsonl"
    write_predictions_jsonl(bad, [prediction_record("nope.png", "Milk", 1, np.eye(3), [0, 0, 1])])
    assert main(["evaluate", "-p", str(bad), "-d", str(data), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "line 1: image 'nope.png' is not in the dataset" in err and "\n" == err[-1] and err.count("\n") == 1
    ok = tmp_path / "ok.jsonl"
    write_predictions_jsonl(ok, predictions_mixed())
    mesh = tmp_path / "thing.obj"
    mesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    assert main(["evaluate", "-p", str(ok), "-d", str(data), "--mesh", str(mesh),
                 "--out", str(tmp_path / "o")]) == 2
    assert "NAME=PATH" in capsys.readouterr().err


def test_mesh_models_use_the_mesh_and_centre_the_catalog_symmetries(tmp_path):
    import trimesh

    mesh_path = tmp_path / "Tuna.ply"
    trimesh.creation.cylinder(radius=0.042, height=0.034, sections=48).apply_transform(
        trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0])).apply_translation(
        [0.0, 0.0, 0.01]).export(mesh_path)
    models = load_models(["Tuna", "Milk"], [str(mesh_path)], mesh_units="m")
    tuna, milk = models["Tuna"], models["Milk"]
    assert tuna.source == f"mesh {mesh_path}" and not tuna.procedural
    assert milk.procedural and milk.source.startswith("procedural cuboid (catalog size")
    assert tuna.points.shape == (500, 3)
    # an object outside the catalog without a mesh: the cuboid its data records, else refused
    widget = load_models(["Widget"], recorded_sizes={"Widget": (np.array([0.1, 0.02, 0.05]), tmp_path)})["Widget"]
    assert widget.procedural and widget.source.startswith("procedural cuboid (recorded size")
    np.testing.assert_allclose(widget.points.max(0) - widget.points.min(0), [0.1, 0.02, 0.05], atol=0.01)
    with pytest.raises(UnknownObjectError, match="'Widget' is not a HOPE object and no mesh was given"):
        load_models(["Widget"])
    assert tuna.diameter == pytest.approx(np.hypot(0.084, 0.034), rel=0.02)
    # the mesh is centred at z = 0.01: its symmetries turn about that centre, so a rotation of
    # the object about its own (vertical) axis costs nothing under MeanSSD
    R_e = rot("y", 57)
    t_e = np.array([0.0, 0.0, 0.01]) - R_e @ np.array([0.0, 0.0, 0.01])
    assert metrics.mean_ssd(R_e, t_e, np.eye(3), np.zeros(3), tuna.points,
                               tuna.symmetries) == pytest.approx(0.0, abs=1e-9)


def test_demo_box_model_and_frame_matching(tmp_path):
    """The demo box as evaluate (and the demo) load it: its model_info.json gives the cuboid's
    flips, so a pose turned 180 degrees is right under MeanSSD. ``match_frame`` (what
    ``dope-hope demo`` counts) matches as ``evaluate`` does: a wrong top-scoring pose does not
    hide a right one, and the rest stays paired for display."""
    from types import SimpleNamespace

    from dope_hope.demo_object import write_demo_object
    from dope_hope.evaluation.matching import match_frame, pose_error

    mesh = write_demo_object(tmp_path / "mesh")
    model = load_models(["DemoBox"], [str(mesh)])["DemoBox"]
    assert model.source == f"mesh {mesh} + symmetries {mesh.parent / 'model_info.json'}"
    assert model.symmetries.shape == (4, 4, 4)
    gt = ObjectAnnotation(class_name="DemoBox", R=np.eye(3), t=np.array([0.0, 0.0, 0.6]))
    assert pose_error("meanssd", rot("y", 180), gt.t, gt, model) == pytest.approx(0.0, abs=1e-9)
    assert pose_error("add", rot("y", 180), gt.t, gt, model) > 0.02

    def est(dz: float, score: float):
        return SimpleNamespace(R=np.eye(3), t=gt.t + [0.0, 0.0, dz], score=score)

    m = match_frame([est(0.05, 0.9), est(0.001, 0.5), est(0.2, 0.1)], [gt], model)
    assert m.found and m.estimate_of_gt.tolist() == [1] and m.unpaired == 2
    m = match_frame([est(0.05, 0.9)], [gt, ObjectAnnotation("DemoBox", np.eye(3), np.array([0.3, 0.0, 0.6]))],
                    model)
    assert not m.found and m.estimate_of_gt.tolist() == [0, -1] and m.correct.tolist() == [False, False]


def test_dataset_without_frames_is_an_input_error(tmp_path):
    with pytest.raises(InputFileError, match="no dope-format frames"):
        load_dataset(tmp_path, "dope")


def write_bop_dataset(root):
    """hope/test/000001 with one image: two Ketchup instances (visibility 0.9 and 0.5)."""
    scene = root / "test" / "000001"
    (scene / "rgb").mkdir(parents=True)
    write_rgb(scene / "rgb" / "000000.png", np.zeros((H, W, 3), np.uint8))
    poses = [(np.eye(3), [-0.1, 0.0, 0.9]), (rot("y", 90), [0.12, 0.0, 1.0])]
    (scene / "scene_camera.json").write_text(json.dumps(
        {"0": {"cam_K": K.ravel().tolist(), "depth_scale": 1.0}}))
    (scene / "scene_gt.json").write_text(json.dumps({"0": [
        {"obj_id": 11, "cam_R_m2c": R.ravel().tolist(), "cam_t_m2c": (1000 * np.array(t)).tolist()}
        for R, t in poses]}))
    (scene / "scene_gt_info.json").write_text(json.dumps({"0": [
        {"visib_fract": v, "bbox_visib": [0, 0, 10, 10]} for v in (0.9, 0.5)]}))
    (root / "test_targets_bop19.json").write_text(json.dumps(
        [{"scene_id": 1, "im_id": 0, "obj_id": 11, "inst_count": 1}]))
    return poses


@pytest.mark.parametrize("scores,expected", [((0.9, 0.5), 1.0), ((0.5, 0.9), 0.0)])
def test_bop_dataset_with_targets_file_and_csv_predictions(tmp_path, scores, expected):
    from dope_hope.io.bop_csv import BopEstimate, write_bop_csv

    # not named "hope": MSPD takes the width of this 80-pixel image, not HOPE's 1920
    poses = write_bop_dataset(tmp_path / "tiny")
    # two perfect estimates, one per instance; inst_count = 1 keeps only the top-scoring one,
    # and only the most visible instance (the first) is a valid target
    csv_path = tmp_path / "mine_hope-test.csv"
    write_bop_csv(csv_path, [BopEstimate(1, 0, 11, s, R, np.array(t), 0.1)
                             for s, (R, t) in zip(scores, poses)])
    s = run_evaluation(EvalConfig(predictions=[csv_path], dataset=tmp_path / "tiny", fmt="bop",
                                        out=tmp_path / "o"), log=lambda _: None)
    bop = s["methods"]["mine"]["bop19"]
    assert bop["targets"] == 1 and bop["gt_valid"] == 1
    assert bop["ar_mssd"] == pytest.approx(expected) and bop["ar_mspd"] == pytest.approx(expected)
    assert bop["ar_vsd"] is None
    # the HOPE table counts both instances and both detections
    row = read_rows(tmp_path / "o" / "per_object_mine.csv")[0]
    assert (row["object"], row["gt"], row["recall_2cm"]) == ("Ketchup", "2", "1.0")


# ----------------------------------------------------------------------------- BOP19 = toolkit
SQUARE_PLY = ("ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
              "property float z\nend_header\n-50 -50 0\n50 -50 0\n-50 50 0\n50 50 0\n")


def write_hope_bop(root, R_gt_stored):
    """hope/test/000001 image 0 (no rgb, no depth): one Ketchup (obj 11) at t = (0, 0, 1000) mm
    with the stored rotation ``R_gt_stored``; models_eval/obj_000011.ply is a point cloud (a
    100 mm flat square, 4 vertices) with a models_info diameter of 100 mm."""
    scene = root / "test" / "000001"
    scene.mkdir(parents=True)
    K_hope = [1000.0, 0.0, 960.0, 0.0, 1000.0, 540.0, 0.0, 0.0, 1.0]
    (scene / "scene_camera.json").write_text(json.dumps({"0": {"cam_K": K_hope, "depth_scale": 1.0}}))
    (scene / "scene_gt.json").write_text(json.dumps({"0": [
        {"obj_id": 11, "cam_R_m2c": list(R_gt_stored), "cam_t_m2c": [0.0, 0.0, 1000.0]}]}))
    (scene / "scene_gt_info.json").write_text(json.dumps({"0": [{"visib_fract": 1.0}]}))
    (root / "test_targets_bop19.json").write_text(json.dumps(
        [{"scene_id": 1, "im_id": 0, "obj_id": 11, "inst_count": 1}]))
    (root / "models_eval").mkdir()
    (root / "models_eval" / "obj_000011.ply").write_text(SQUARE_PLY)
    (root / "models_eval" / "models_info.json").write_text(json.dumps({"11": {"diameter": 100.0}}))


@pytest.mark.parametrize("R_gt_stored,ar_mssd", [
    ((1, 0, 0, 0, 1, 0, 0, 0, 1), 0.8),
    # stored GT rotations are used as stored: x scaled by 1 + 1e-6 makes the MSSD 15.00005 mm
    ((1.000001, 0, 0, 0, 1, 0, 0, 0, 1), 0.7),
])
def test_bop19_ties_and_inputs_as_the_toolkit(tmp_path, R_gt_stored, ar_mssd):
    """By hand from the toolkit's definitions: the estimate is the GT shifted 15 mm along x.
    MSSD = 15 mm = 0.15 x the 100 mm diameter, correct for thresholds np.arange(0.05, 0.51,
    0.05)[2:] (0.15 < 0.15000000000000002): AR_MSSD 0.8 (0.7 with rounded thresholds).
    MSPD: every vertex at depth 1000 with f = 1000 moves 15 px; x 640 / 1920 (HOPE's width,
    not from image files: there are none) = 5.0, not < 5: AR_MSPD 0.9. Estimates that are not
    of a target (object 12; an image not in the dataset) are ignored, time -1 is "unknown"."""
    root = tmp_path / "hope"
    write_hope_bop(root, R_gt_stored)
    csv_path = tmp_path / "mine_hope-test.csv"
    csv_path.write_text("scene_id,im_id,obj_id,score,R,t,time\n"
                        "1,0,11,0.9,1 0 0 0 1 0 0 0 1,15 0 1000,-1\n"
                        "1,0,12,0.9,1 0 0 0 1 0 0 0 1,0 0 1000,-1\n"
                        "2,500,11,0.9,1 0 0 0 1 0 0 0 1,0 0 1000,-1\n")
    logs = []
    s = run_evaluation(EvalConfig(predictions=[csv_path], dataset=root, fmt="bop",
                                  models_dir=root / "models_eval", out=tmp_path / "o"),
                       log=logs.append)
    bop = s["methods"]["mine"]["bop19"]
    assert bop["ar_mssd"] == ar_mssd and bop["ar_mspd"] == 0.9
    assert bop["recalls"]["mspd"] == [0.0] + [1.0] * 9
    assert bop["ar_vsd"] is None and bop["ar"] == np.mean([ar_mssd, 0.9])
    assert any("1 estimates of images that are not in" in m for m in logs)
    assert any("1 of 2 estimates are not of a target" in n for n in bop["notes"])
    assert any("MSPD image width: 1920 px" in n for n in bop["notes"])


def test_bop19_details_are_the_toolkits_errors_and_matches(tmp_path):
    """details=True gives what the toolkit writes: errors_000001.json {"est_id": 0, "errors":
    {"0": [15.0]}} for MSSD (mm) and MSPD (px: 15 mm at 1000 mm, f = 1000), and the
    matches_th=*.json of the valid GT: est 0 from 0.15000000000000002 x diameter (MSSD) and
    from 10 px (MSPD: 640 / 1920 x 15 = 5.0 is not < 5) on."""
    from dope_hope.evaluation.bop19 import bop19_average_recall
    from dope_hope.evaluation.datasets import assign_predictions
    from dope_hope.io.predictions import read_predictions

    root = tmp_path / "hope"
    write_hope_bop(root, (1, 0, 0, 0, 1, 0, 0, 0, 1))
    csv_path = tmp_path / "mine_hope-test.csv"
    csv_path.write_text("scene_id,im_id,obj_id,score,R,t,time\n"
                        "1,0,11,0.9,1 0 0 0 1 0 0 0 1,15 0 1000,-1\n")
    dataset = load_dataset(root, "bop")
    by_frame, _ = assign_predictions(dataset, read_predictions(csv_path)[0], csv_path)
    models = load_models(["Ketchup"], models_dir=root / "models_eval")
    d = bop19_average_recall(dataset, by_frame, models, details=True)["details"]
    assert d["pairs"] == [{"scene_id": 1, "im_id": 0, "obj_id": 11, "est_id": 0, "gt_id": 0,
                           "mssd": 15.0, "mspd": 15.0, "vsd": None}]
    assert [r["est_id"] for r in d["matches"]["mssd"]] == [-1, -1] + [0] * 8
    assert [r["est_id"] for r in d["matches"]["mspd"]] == [-1] + [0] * 9
    assert {(r["scene_id"], r["im_id"], r["gt_id"]) for r in d["matches"]["mssd"]} == {(1, 0, 0)}
    # the same files in a folder that is not models_eval/ (the full models, for the toolkit
    # another input): said so
    (root / "models_eval").rename(root / "models")
    models = load_models(["Ketchup"], models_dir=root / "models")
    notes = bop19_average_recall(dataset, by_frame, models)["notes"]
    assert any("with DATASET/models_eval/; not from a models_eval folder: Ketchup" in n for n in notes)


def test_bop_models_use_every_vertex_of_the_file_in_millimetres(tmp_path):
    root = tmp_path / "hope"
    write_hope_bop(root, (1, 0, 0, 0, 1, 0, 0, 0, 1))
    m = load_models(["Ketchup"], models_dir=root / "models_eval")["Ketchup"]
    np.testing.assert_array_equal(m.bop.points, [[-50, -50, 0], [50, -50, 0], [-50, 50, 0], [50, 50, 0]])
    assert m.bop.faces is None and m.bop.diameter == 100.0 and m.bop.exact
    np.testing.assert_array_equal(m.bop.symmetries, np.eye(4)[None])
    # the tables keep their metres (the 4 points are all the cloud has)
    assert m.diameter == pytest.approx(0.1) and m.points.shape == (4, 3)
    # a --symmetries declaration beside models_info's entry would be ignored: refused instead
    decl = tmp_path / "sym.json"
    decl.write_text(json.dumps({"symmetries_discrete": [np.diag([1.0, -1.0, -1.0, 1.0]).ravel().tolist()]}))
    with pytest.raises(ConfigError, match="--symmetries for Ketchup would be ignored"):
        load_models(["Ketchup"], models_dir=root / "models_eval", symmetry_args=[f"Ketchup={decl}"])


def test_official_dope_output_folder_is_scored_in_the_mesh_frame(tmp_path):
    """NVIDIA's inference output (legacy-frame poses of the cuboid, cm) scores like the same
    poses given in the mesh frame; the folder's JSON paths name the images."""
    from dope_hope.geometry import LEGACY_TO_MESH

    data = write_dataset(tmp_path / "data")
    folder = tmp_path / "output" / "net_all_0060"
    for k, objs in GT.items():
        out = [{"class": c, "location": (100.0 * np.asarray(t)).tolist(),
                "quaternion_xyzw": Rotation.from_matrix(R @ LEGACY_TO_MESH).as_quat().tolist(),
                "projected_cuboid": [[0.0, 0.0]] * 9} for c, R, t, _ in objs]
        folder.mkdir(parents=True, exist_ok=True)
        (folder / f"{k:06d}.json").write_text(json.dumps({"camera_data": {}, "objects": out}))
    out = tmp_path / "out"
    assert main(["evaluate", "-p", str(folder), "-d", str(data), "--out", str(out), "--no-progress"]) == 0
    rows = read_rows(out / "per_object_net_all_0060.csv")
    assert all(float(r["recall_2cm"]) == 1.0 and float(r["precision_2cm"]) == 1.0 for r in rows)
    # taken as cuboid-frame poses instead, the rotations are off
    assert main(["evaluate", "-p", str(folder), "-d", str(data), "--out", str(out), "--no-progress",
                 "--official-frame", "cuboid"]) == 0
    rows = {r["object"]: r for r in read_rows(out / "per_object_net_all_0060.csv")}
    assert float(rows["Milk"]["recall_2cm"]) == 0.0


def test_cuboid_centre_poses_move_to_the_mesh_origin(tmp_path):
    """The official pose places the box centre; a mesh whose box is off its origin gets
    t - R c, so a perfect official estimate has zero error."""
    import trimesh

    from dope_hope.io.predictions import Prediction

    mesh_path = tmp_path / "Widget.ply"
    trimesh.creation.box(extents=[0.04, 0.1, 0.02]).apply_translation([0.01, 0.02, -0.005]).export(mesh_path)
    models = load_models(["Widget"], [f"Widget={mesh_path}"], mesh_units="m")
    R, t_origin = rot("x", 40), np.array([0.05, 0.0, 0.7])
    centre = R @ np.array([0.01, 0.02, -0.005]) + t_origin
    pred = Prediction("000000", "Widget", 1.0, R, centre.copy(), origin="cuboid")
    cuboid_centres_to_origins([pred], models)
    np.testing.assert_allclose(pred.t, t_origin, atol=1e-8)  # PLY stores float32
    assert pred.origin == "mesh"
    cuboid_centres_to_origins([pred], models)  # done once only
    np.testing.assert_allclose(pred.t, t_origin, atol=1e-8)  # PLY stores float32


def test_declared_symmetries_of_a_custom_object_are_used(tmp_path):
    """model_info.json beside a custom mesh (or --symmetries NAME=FILE) gives the evaluation's
    symmetries, discretized as the BOP toolkit does; without one a custom object has those
    found on its mesh (here: continuous about z and a flip)."""
    import trimesh

    from dope_hope.io.symmetries import read_declaration
    from dope_hope.symmetry.transforms import symmetries_from_models_info

    folder = tmp_path / "widget"
    folder.mkdir()
    mesh_path = folder / "widget.ply"
    trimesh.creation.cylinder(radius=20.0, height=80.0, sections=64).export(mesh_path)  # mm, axis z
    flip = np.diag([1.0, -1.0, -1.0, 1.0]).ravel().tolist()
    found = load_models(["Widget"], [f"Widget={mesh_path}"])["Widget"]
    assert "+ symmetries detected on the mesh: continuous about z" in found.source
    assert found.found_symmetries.startswith("detected on the mesh: continuous about z")
    assert len(found.symmetries) == 2 * math.ceil(math.pi / 0.01)
    (folder / "model_info.json").write_text(json.dumps(
        {"symmetries_discrete": [flip], "symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]}))
    model = load_models(["Widget"], [f"Widget={mesh_path}"])["Widget"]
    assert model.source.endswith(f"+ symmetries {folder / 'model_info.json'}")
    assert len(model.symmetries) == 2 * math.ceil(math.pi / 0.01)
    decl = read_declaration(folder / "model_info.json")
    np.testing.assert_array_equal(model.symmetries, symmetries_from_models_info(decl.entry, unit=0.001))
    np.testing.assert_array_equal(model.bop.symmetries, symmetries_from_models_info(decl.entry, unit=1.0))
    # a turn about the declared axis costs nothing under MSSD
    R_e = rot("z", 73.0)
    err = metrics.mssd(R_e, np.zeros(3), np.eye(3), np.zeros(3), model.points, model.symmetries)
    assert err < 0.02 * math.pi / 315 + 1e-9
    other = tmp_path / "only_flip.json"
    other.write_text(json.dumps({"symmetries_discrete": [flip]}))
    flipped = load_models(["Widget"], [f"Widget={mesh_path}"], symmetry_args=[f"Widget={other}"])["Widget"]
    assert len(flipped.symmetries) == 2
