"""BOP19 parity: dope-hope's AR_MSSD / AR_MSPD / AR_VSD against the BOP toolkit's own pipeline.

Builds a small HOPE-format BOP dataset (``hope/test``, 1920x1080, models_eval PLYs in mm with
``models_info.json`` diameters and symmetries, ``scene_gt``/``scene_gt_info``/
``scene_camera``, 16-bit depth, ``test_targets_bop19.json``) and a submission CSV with the
cases where a re-implementation can drift: exact threshold ties (a 15 mm shift of an object
whose models_info diameter is 100 mm: MSSD 0.15 x diameter, MSPD 5.0 px at width 640),
multi-instance targets with equal scores, GT instances that are not valid (less visible than
the ``inst_count`` most visible), non-target objects and images, time -1, continuous and
discrete symmetries (stored 0.866 entries), GT and estimate rotations stored with few decimals
(not exactly orthonormal), depth_scale 0.1 and 1, estimates far away (MSSD short-cut, no
sphere-projection overlap), random pose noise spreading the errors over the thresholds.

Then it runs the toolkit (a user's checkout of thodan/bop_toolkit: ``scripts/eval_bop19_pose.py``,
or with ``--no-vsd`` its ``eval_calc_errors.py`` + ``eval_calc_scores.py`` exactly as that
driver calls them) and ``dope_hope.evaluation.bop19.bop19_average_recall`` on the same files,
and prints the ARs side by side, their difference, and the number of per-pair disagreements:
raw errors of every (estimate, GT) pair (``errors_*.json``) and the matched estimate of
every valid GT at every threshold (``matches_*.json``). Exit status 1 on any disagreement
(an AR difference above 1e-12 or one differing pair).

The toolkit needs numpy, scipy, imageio, pypng, pytz, and for VSD vispy (EGL: on a headless
machine with Mesa, ``EGL_PLATFORM=surfaceless`` is set unless already set). ``--python``
names the interpreter that has them (the toolkit's driver starts ``python`` from PATH: that
interpreter's folder is put first on PATH).

    python bench/bop_parity.py --toolkit /path/to/bop_toolkit [--python PY] [--no-vsd]
        [--work DIR] [--seed 0]
"""
from __future__ import annotations

import argparse
import glob
import json
import math
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from scipy.spatial.distance import pdist
from scipy.spatial.transform import Rotation

W, H = 1920, 1080
RESULT = "parity_hope-test"
K_TIES = np.array([[1000.0, 0.0, 960.0], [0.0, 1000.0, 540.0], [0.0, 0.0, 1.0]])
K_HOPE = np.array([[1390.53, 0.0, 964.957], [0.0, 1386.99, 522.586], [0.0, 0.0, 1.0]])


# ----------------------------------------------------------------------------- models (mm)
def cube(half: float = 50.0):
    v = np.array([[x, y, z] for x in (-half, half) for y in (-half, half) for z in (-half, half)])
    f = [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
         [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]
    return v, np.array(f)


def prism(radius: float, height: float, sides: int):
    """Closed prism about z (a cylinder for many sides): rings at z = +-height / 2 + caps."""
    a = 2 * np.pi * np.arange(sides) / sides
    ring = np.stack([radius * np.cos(a), radius * np.sin(a)], axis=1)
    v = np.concatenate([np.c_[ring, np.full(sides, -height / 2)], np.c_[ring, np.full(sides, height / 2)],
                        [[0, 0, -height / 2], [0, 0, height / 2]]])
    f = []
    for i in range(sides):
        j = (i + 1) % sides
        f += [[i, j, sides + j], [i, sides + j, sides + i],
              [2 * sides, j, i], [2 * sides + 1, sides + i, sides + j]]
    return v, np.array(f)


def ketchup_or_stand_in():
    """The HOPE Ketchup scan (shared data, cm -> mm) when present, else an irregular box."""
    shared = os.environ.get("DOPE_HOPE_SHARED_DATA")
    path = Path(shared) / "hope_ketchup" / "textured_simple.obj" if shared else None
    if path is not None and path.is_file():
        from dope_hope.io.meshes import load_mesh

        m = load_mesh(path, units="cm")
        return np.asarray(m.vertices) * 1000.0, np.asarray(m.faces), "HOPE Ketchup scan"
    v, f = cube(1.0)
    return v * [32.25, 74.3, 21.7] + [1.7, 3.1, -0.9], f, "irregular box (no shared data)"


def write_ply(path: Path, v: np.ndarray, f: np.ndarray, binary: bool = False) -> None:
    """ASCII (coordinates as repr of the float64) or binary little-endian float32."""
    fmt = "binary_little_endian" if binary else "ascii"
    header = ["ply", f"format {fmt} 1.0", f"element vertex {len(v)}", "property float x",
              "property float y", "property float z", f"element face {len(f)}",
              "property list uchar int vertex_indices", "end_header"]
    if binary:
        face = np.zeros(len(f), dtype=[("n", "u1"), ("i", "<i4", (3,))])
        face["n"], face["i"] = 3, f
        path.write_bytes(("\n".join(header) + "\n").encode() + np.asarray(v, "<f4").tobytes()
                         + face.tobytes())
        return
    lines = ["ply", "format ascii 1.0", f"element vertex {len(v)}", "property float x",
             "property float y", "property float z", f"element face {len(f)}",
             "property list uchar int vertex_indices", "end_header"]
    lines += [" ".join(repr(float(c)) for c in p) for p in v]
    lines += [f"3 {a} {b} {c}" for a, b, c in f]
    path.write_text("\n".join(lines) + "\n")


def rz(deg: float) -> np.ndarray:
    return Rotation.from_euler("z", deg, degrees=True).as_matrix()


# ----------------------------------------------------------------------------- dataset
def build(root: Path, seed: int) -> tuple[Path, str]:
    """Write ``root/hope`` and ``root/results/<RESULT>.csv``; returns (csv path, notes)."""
    rng = np.random.default_rng(seed)
    ds = root / "hope"
    meshes, k_name = write_models(ds / "models_eval")
    scenes, targets = scene_poses(rng)
    write_scenes(ds, scenes, targets, meshes)
    csv, n = write_estimates(root, rng, scenes)
    return csv, f"{n} estimates, {len(targets)} targets, ketchup: {k_name}"


def write_models(models_dir: Path) -> tuple[dict, str]:
    """The BOP models (mm) and models_info.json: a cube, a cylinder-like prism, a hexagonal
    prism, the Ketchup (or its stand-in) and small boxes for the other HOPE ids; returns
    ({obj_id: (vertices, faces)}, the Ketchup's source)."""
    models_dir.mkdir(parents=True)
    k_v, k_f, k_name = ketchup_or_stand_in()
    hex60 = [[0.5, -0.866, 0, 0, 0.866, 0.5, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1],
             [-0.5, -0.866, 0, 0, 0.866, -0.5, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1],
             [-1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1],
             [-0.5, 0.866, 0, 0, -0.866, -0.5, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1],
             [0.5, 0.866, 0, 0, -0.866, 0.5, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]]
    meshes = {1: cube(), 2: prism(30.0, 100.0, 24), 3: prism(25.0, 40.0, 6), 11: (k_v, k_f)}
    info = {1: {"diameter": 100.0},  # stated, not the cube's diagonal: the 15 mm tie case
            2: {"diameter": float(pdist(meshes[2][0]).max()),
                "symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}],
                "symmetries_discrete": [[1, 0, 0, 0, 0, -1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1]]},
            3: {"diameter": float(pdist(meshes[3][0]).max()), "symmetries_discrete": hex60},
            11: {"diameter": float(pdist(k_v).max())}}
    for oid in range(1, 29):  # the toolkit loads every HOPE object: small boxes stand in
        if oid not in meshes:
            meshes[oid] = cube(20.0 + oid)
            info[oid] = {"diameter": float(pdist(meshes[oid][0]).max())}
    for oid, (v, f) in meshes.items():
        write_ply(models_dir / f"obj_{oid:06d}.ply", v, f, binary=oid == 3)
    (models_dir / "models_info.json").write_text(json.dumps({str(k): v for k, v in info.items()}))

    return meshes, k_name


def scene_poses(rng: np.random.Generator) -> tuple[dict, list]:
    """(scenes: scene_id -> (K, depth_scale, {im_id: [(obj_id, R, t, visib_fract)]}),
    targets: [(scene_id, im_id, obj_id, inst_count)])."""
    def pose(R, t):
        return np.asarray(R, float), np.asarray(t, float)

    def rand_pose(z):
        return pose(Rotation.random(rng=rng).as_matrix(),
                    [rng.uniform(-250, 250), rng.uniform(-150, 150), z])

    scenes = {
        1: (K_TIES, 1.0, {
            0: [(1, *pose(np.eye(3), [0, 0, 1000]), 1.0)],
            1: [(1, *pose(rz(30), [-200, 0, 1100]), 0.8), (1, *pose(rz(-20), [200, 50, 1200]), 0.7),
                (2, *pose(Rotation.from_euler("x", 80, degrees=True).as_matrix(), [0, -200, 1000]), 0.9),
                (3, *pose(rz(10), [0, 250, 900]), 0.6)],
            2: [(1, *pose(np.eye(3), [0, 0, 1000]), 1.0)],
            3: [(1, *pose(rz(5), [-300, 0, 1000]), 0.9), (1, *pose(rz(50), [0, 0, 1100]), 0.05),
                (1, *pose(rz(-40), [300, 0, 1000]), 0.6)],
            4: [(1, *pose(np.eye(3), [-150, 0, 1000]), 0.7), (1, *pose(rz(15), [150, 0, 1000]), 0.7)],
            5: [(1, *pose(np.eye(3), [-60, 0, 1000]), 0.8), (1, *pose(np.eye(3), [60, 0, 1000]), 0.8)]}),
        2: (K_HOPE, 0.1, {
            0: [(11, *rand_pose(800), 0.95), (11, *rand_pose(900), 0.4), (3, *rand_pose(850), 0.7),
                (2, *rand_pose(950), 0.8), (1, *rand_pose(1000), 0.3)],
            5: [(11, *rand_pose(1000), 0.9)],
            7: [(2, *rand_pose(700), 0.85), (2, *rand_pose(1100), 0.85), (3, *rand_pose(900), 0.5)]}),
    }
    targets = [(1, 0, 1, 1), (1, 1, 1, 2), (1, 1, 2, 1), (1, 3, 1, 2), (1, 4, 1, 1), (1, 5, 1, 2),
               (2, 0, 11, 2), (2, 0, 3, 1), (2, 0, 2, 1), (2, 5, 11, 1), (2, 7, 2, 2), (2, 7, 3, 1)]
    return scenes, targets


def write_scenes(ds: Path, scenes: dict, targets: list, meshes: dict) -> None:
    """scene_camera / scene_gt / scene_gt_info and rendered depth (with a stripe without
    depth, a surface 15 mm in front of the cube and an occluder) of each scene, and the targets."""
    from dope_hope.io.images import write_rgb
    from dope_hope.render.depth import default_renderer

    ren = default_renderer()
    for sid, (K, scale, ims) in scenes.items():
        sd = ds / "test" / f"{sid:06d}"
        (sd / "depth").mkdir(parents=True)
        cam, gt, gt_info = {}, {}, {}
        for im_id, objs in ims.items():
            cam[str(im_id)] = {"cam_K": K.ravel().tolist(), "depth_scale": scale}
            # stored like the BOP files: rotations with 8 decimals (not exactly orthonormal)
            gt[str(im_id)] = [{"obj_id": o, "cam_R_m2c": [round(x, 8) for x in R.ravel()],
                               "cam_t_m2c": [round(x, 6) for x in t]} for o, R, t, _ in objs]
            gt_info[str(im_id)] = [{"visib_fract": v} for *_, v in objs]
            depth = np.full((H, W), 1500.0)
            for o, R, t, _ in objs:
                d = ren.render_depth(meshes[o], R, t, K, W, H)
                depth = np.where((d > 0) & (d < depth), d, depth)
            depth[100:160, :] = 0.0                       # a stripe without depth
            depth[500:560, 900:1000] = 935.0              # 15 mm in front of the cube's face
            depth[:, 1200:1260] -= 200.0                  # an occluder
            write_rgb(sd / "depth" / f"{im_id:06d}.png",
                      np.clip(np.round(depth / scale), 0, 65535).astype(np.uint16))
        for name, content in (("scene_camera", cam), ("scene_gt", gt), ("scene_gt_info", gt_info)):
            (sd / f"{name}.json").write_text(json.dumps(content))
    (ds / "test_targets_bop19.json").write_text(json.dumps(
        [{"scene_id": s, "im_id": i, "obj_id": o, "inst_count": n} for s, i, o, n in targets]))


def write_estimates(root: Path, rng: np.random.Generator, scenes: dict) -> tuple[Path, int]:
    """``root/results/<RESULT>.csv``: the tie cases of scene 1 and noisy estimates of scene 2;
    returns (its path, the number of estimates)."""
    rows = []

    def est(sid, im, oid, score, R, t, time=-1):
        rows.append(f"{sid},{im},{oid},{score},{' '.join(f'{x:.6f}' for x in np.ravel(R))},"
                    f"{' '.join(f'{x:.4f}' for x in np.ravel(t))},{time}")

    gt_of = {(s, i): objs for s, (_, _, ims) in scenes.items() for i, objs in ims.items()}
    # ties: the cube shifted 15 mm: MSSD 15 = 0.15 x 100 mm; MSPD 15 px x 640 / 1920 = 5.0
    est(1, 0, 1, 0.9, np.eye(3), [15, 0, 1000])
    est(1, 0, 12, 0.9, np.eye(3), [0, 0, 1000])                  # not a target object
    est(1, 2, 1, 0.9, np.eye(3), [0, 0, 1000])                   # not a target image
    est(7, 0, 1, 0.9, np.eye(3), [0, 0, 1000])                   # not in the dataset
    (_, R0, t0, _), (_, R1, t1, _), (_, Rc, tc, _), (_, Rh, th, _) = gt_of[(1, 1)]
    est(1, 1, 1, 0.8, R0, t0 + [10, 0, 0])                       # equal scores: file order
    est(1, 1, 1, 0.8, R1, t1 + [0, 30, 0])
    est(1, 1, 1, 0.5, R0, t0 + [2, 0, 0])
    est(1, 1, 2, 0.7, Rc @ rz(37) @ np.diag([1, -1, -1]), tc + [0, 4, 0])  # symmetric turn + flip
    est(1, 1, 3, 0.7, Rh @ rz(60), th)                           # not a target (hex in 1/1)
    for k, (_, R, t, _) in enumerate(gt_of[(1, 3)]):  # the invisible GT is not valid; equal
        est(1, 3, 1, 0.5, R, t + [0, 0, 5.0 * k])      # scores: the third is past inst_count 2
    (_, R0, t0, _), (_, R1, t1, _) = gt_of[(1, 4)]      # equally visible GT, inst_count 1:
    est(1, 4, 1, 0.9, R1, t1)                          # only gt 0 is valid; this one is top
    est(1, 4, 1, 0.5, R0, t0 + [5, 0, 0])
    est(1, 5, 1, 0.9, np.eye(3), [0, 0, 1000])         # equal errors to both GT: gt 0 first,
    est(1, 5, 1, 0.8, np.eye(3), [-60, 0, 1000])       # then this one only reaches gt 1 at 40 px
    for (s, i), objs in gt_of.items():
        if s != 2:
            continue
        for o, R, t, _ in objs:
            for _ in range(3):                                   # noise over the thresholds
                dR = Rotation.from_rotvec(rng.normal(size=3) * math.radians(rng.uniform(0, 12)) / math.sqrt(3))
                est(s, i, o, round(float(rng.uniform(0.1, 1.0)), 2), R @ dR.as_matrix(),
                    t + rng.normal(size=3) * rng.uniform(0, 25), time=0.25)
            if o == 3:
                est(s, i, o, 0.99, R @ rz(120), t, time=0.25)   # a discrete symmetry (0.866)
            if o == 2:
                est(s, i, o, 0.3, R @ np.diag([1, -1, -1]) @ rz(200), t + [1, 1, 1], time=0.25)
    est(2, 5, 11, 0.95, np.eye(3), [900, 0, 1000], time=0.25)    # far away: short-cuts
    results = root / "results"
    results.mkdir()
    csv = results / f"{RESULT}.csv"
    csv.write_text("scene_id,im_id,obj_id,score,R,t,time\n" + "\n".join(rows) + "\n")
    return csv, len(rows)




# ----------------------------------------------------------------------------- toolkit
def run_toolkit(toolkit: Path, python: str, root: Path, vsd: bool) -> None:
    env = dict(os.environ, BOP_PATH=str(root), PYTHONPATH=str(toolkit),
               PATH=os.path.dirname(os.path.abspath(python)) + os.pathsep + os.environ.get("PATH", ""))
    env.setdefault("EGL_PLATFORM", "surfaceless")
    common = [f"--results_path={root / 'results'}", f"--eval_path={root / 'eval'}",
              "--targets_filename=test_targets_bop19.json"]

    def call(args):
        r = subprocess.run([python] + args, env=env, cwd=toolkit, capture_output=True, text=True)
        if r.returncode != 0:
            sys.exit(f"toolkit failed: {' '.join(args[:1])}\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}")

    if vsd:
        call([str(toolkit / "scripts" / "eval_bop19_pose.py"), "--renderer_type=vispy",
              f"--result_filenames={RESULT}.csv", "--num_workers=1"] + common)
        return
    # eval_bop19_pose.py's own calls for MSSD and MSPD (it always runs VSD as well)
    for kind, ths in (("mssd", np.arange(0.05, 0.51, 0.05)), ("mspd", np.arange(5, 51, 5))):
        call([str(toolkit / "scripts" / "eval_calc_errors.py"), "--n_top=-1", f"--error_type={kind}",
              f"--result_filenames={RESULT}.csv", "--renderer_type=vispy", "--max_sym_disc_step=0.01",
              "--skip_missing=1", "--num_workers=1"] + common)
        for th in ths:
            call([str(toolkit / "scripts" / "eval_calc_scores.py"),
                  f"--error_dir_paths={RESULT}/error={kind}_ntop=-1", f"--eval_path={root / 'eval'}",
                  "--targets_filename=test_targets_bop19.json", "--visib_gt_min=-1",
                  f"--correct_th_{kind}={th}"])


def _num(path: str, key: str) -> float:
    return float(re.search(rf"{key}=([-0-9.]+)", path).group(1))


def read_toolkit(root: Path, vsd: bool) -> dict:
    """Recalls, errors and matches from the toolkit's output files."""
    ev = root / "eval" / RESULT
    out = {"recalls": {}, "errors": {}, "matches": {}}
    kinds = ["mssd", "mspd"] + (["vsd"] if vsd else [])
    for kind in kinds:
        dirs = sorted(glob.glob(str(ev / f"error={kind}_ntop=-1*")),
                      key=lambda d: _num(d, "tau") if kind == "vsd" else 0)
        recalls, errors, matches = [], {}, {}
        for k, d in enumerate(dirs):
            for f in glob.glob(os.path.join(d, "errors_*.json")):
                for e in json.loads(Path(f).read_text()):
                    for gt_id, v in e["errors"].items():
                        errors[(e["scene_id"], e["im_id"], e["obj_id"], e["est_id"], int(gt_id), k)] = v[0]
            for j, f in enumerate(sorted(glob.glob(os.path.join(d, "scores_th=*.json")), key=lambda f: _num(f, "th"))):
                recalls.append(json.loads(Path(f).read_text())["recall"])
            for j, f in enumerate(sorted(glob.glob(os.path.join(d, "matches_th=*.json")), key=lambda f: _num(f, "th"))):
                for m in json.loads(Path(f).read_text()):
                    if m["valid"]:
                        matches[(k, j, m["scene_id"], m["im_id"], m["gt_id"])] = m["est_id"]
        out["recalls"][kind] = recalls
        out["errors"][kind] = errors
        out["matches"][kind] = matches
        # AR as eval_bop19_pose.py: np.mean over the list (VSD: tau outer, threshold inner)
        out[f"ar_{kind}"] = float(np.mean(recalls))
    if vsd:
        final = json.loads((ev / "scores_bop19.json").read_text())
        out["ar_final"] = {k: final[f"bop19_average_recall_{k}"] for k in kinds}
        out["ar"] = final["bop19_average_recall"]
    return out


# ----------------------------------------------------------------------------- dope-hope
def run_package(root: Path, csv: Path, vsd: bool) -> dict:
    from dope_hope.evaluation.bop19 import bop19_average_recall
    from dope_hope.evaluation.datasets import assign_predictions, load_dataset
    from dope_hope.evaluation.object_models import load_models
    from dope_hope.io.predictions import read_predictions

    dataset = load_dataset(root / "hope", "bop")
    preds, _ = read_predictions(csv)
    by_frame, _ = assign_predictions(dataset, preds, csv)
    classes = sorted({o.class_name for f in dataset.frames for o in f.objects})
    models = load_models(classes, models_dir=root / "hope" / "models_eval")
    res = bop19_average_recall(dataset, by_frame, models, use_vsd=vsd, details=True)
    errors = {"mssd": {}, "mspd": {}, "vsd": {}}
    for p in res["details"]["pairs"]:
        key = (p["scene_id"], p["im_id"], p["obj_id"], p["est_id"], p["gt_id"])
        errors["mssd"][key + (0,)] = p["mssd"]
        errors["mspd"][key + (0,)] = p["mspd"]
        for k, v in enumerate(p["vsd"] or []):
            errors["vsd"][key + (k,)] = v
    matches = {kind: {(m["tau"] or 0, m["threshold"], m["scene_id"], m["im_id"], m["gt_id"]): m["est_id"]
                      for m in rows} for kind, rows in res["details"]["matches"].items()}
    return {**res, "errors": errors, "matches": matches}


def disagreements(a: dict, b: dict) -> int:
    return sum(1 for k in set(a) | set(b) if k not in a or k not in b or not
               (a[k] == b[k] or (isinstance(a[k], float) and math.isnan(a[k]) and math.isnan(b[k]))))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--toolkit", required=True, type=Path, help="a checkout of thodan/bop_toolkit")
    ap.add_argument("--python", default=sys.executable,
                    help="interpreter for the toolkit (default: this one)")
    ap.add_argument("--no-vsd", action="store_true", help="MSSD and MSPD only (no rendering)")
    ap.add_argument("--work", type=Path, help="work folder (default: a temporary one)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    vsd = not args.no_vsd
    work = args.work or Path(tempfile.mkdtemp(prefix="bop_parity_"))
    work.mkdir(parents=True, exist_ok=True)
    csv, note = build(work, args.seed)
    print(f"dataset: {work / 'hope'} ({note})")
    run_toolkit(args.toolkit.resolve(), args.python, work, vsd)
    tk = read_toolkit(work, vsd)
    pk = run_package(work, csv, vsd)
    bad = 0
    print(f"{'':8} {'toolkit':>20} {'dope-hope':>20} {'difference':>12} {'pairs':>6} {'error diff':>10} "
          f"{'matches':>8} {'match diff':>10}")
    for kind in ["vsd", "mssd", "mspd"] if vsd else ["mssd", "mspd"]:
        t, p = tk[f"ar_{kind}"], pk[f"ar_{kind}"]
        d_err = disagreements(tk["errors"][kind], pk["errors"][kind])
        d_match = disagreements(tk["matches"][kind], pk["matches"][kind])
        bad += (abs(t - p) > 1e-12) + d_err + d_match
        print(f"AR_{kind.upper():5} {t:20.17f} {p:20.17f} {p - t:12.3g} {len(tk['errors'][kind]):6d} "
              f"{d_err:10d} {len(tk['matches'][kind]):8d} {d_match:10d}")
    if vsd:
        bad += abs(tk["ar"] - pk["ar"]) > 1e-12
        print(f"{'AR':8} {tk['ar']:20.17f} {pk['ar']:20.17f} {pk['ar'] - tk['ar']:12.3g}")
    print("PARITY: identical" if not bad else f"PARITY: {bad} disagreement(s)")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
