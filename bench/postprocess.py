"""Post-processing speed: maps -> poses per image, and the depth line search (-LS) per object.

Maps -> poses (``--only-maps``): four decoders on the same belief/affinity maps of 10 boxes
(one object's map set: 9 belief + 16 affinity channels), interleaved in one process (the order
rotates each round), median CPU time per image (``time.process_time`` with OpenCV and torch
on one thread, so other jobs on a shared machine do not count):

* **official**: the official DOPE decoder, ``bench/official_dope.py`` (a transcription of
  NVlabs/Deep_Object_Pose ``ObjectDetector.find_object_poses`` with ``config_pose.yaml``:
  sigma 3, 11x11 weighted means, greedy grouping, complete 9-point objects only,
  ``cv2.solvePnP`` ITERATIVE), fed torch tensors as the network returns them;
* **default**: ``DopePredictor.detections_from_maps`` with ``pose_search="hypotheses"``
  (``maps.decode.corner_candidates`` + ``inference.pose_search.solve_pnp_candidates``);
* **no floor**: the default without the peaks' noise floor (``decode: {noise_sigmas: 0}``:
  every peak above the threshold, as before the floor);
* **groups**: the same with ``pose_search="groups"`` (``maps.decode.decode_maps`` +
  ``inference.pnp.solve_pnp``).

Map sets (``maps.targets.make_targets`` of seeded random Popcorn-box poses at 0.6-1.0 m, every
keypoint at least 32 px inside the image; 640x480 input at stride 8 = 80x60 maps unless
noted; K of a 615-px camera): ideal; Gaussian noise of std 0.01 added to the belief and 0.05
to the affinity; 0.03 / 0.1; 0.1 / 0.3 (heavy: noise blobs pass the 0.1 peak threshold
everywhere); one corner peak (belief and field) missing per box; noise
0.01 / 0.05 + a missing corner + five overlapping pairs of boxes; ideal maps of a 400x400
input (50x50); "confused" maps where corner maps 0-2 of every box also peak, stronger (1.0,
the true peak lowered to 0.7), on its corners 2, 3, 0 with fields pointing at its centroid
(a trained lite net's commonest error). A box is found when a pose's cuboid keypoints lie on
average within 10 % of the cuboid diagonal of the truth (ADD on the nine keypoints), one
pose per box.

-LS: ``depth_line_search`` (coarse 41-step grid + bounded Brent) against a dense grid search
over the same range in 0.1 % steps (the simple way to do it), same cost function, 640x480
depth of a ray-cast box, ~4200 surface points.

-LS + ICP (``--only-icp``): ``dope_hope.refine.icp.icp_refine`` with its ten starts (the default: a
coarse phase on a thinned scene, four finish; the model's nearest points looked up on its
grid) against the same ten starts all on every point, against the exact nearest points
(``icp_refine.nearest: exact``, scipy's cKDTree: the baselines) and against one start, after
the line search, per object: the box's depth as above, the input pose turned 20 deg (random
axis) or 80 deg (about the box's long axis: a lite net's commonest rotation error) and 10 %
too far; time, and how often each ends within 1 deg and 2 mm.

    python bench/postprocess.py [--scenes 5] [--rounds 5] [--repeats 3] [--only-maps | --only-icp]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch
from scipy.spatial.transform import Rotation

from dope_hope.catalog import get_object
from dope_hope.geometry import (
    KEYPOINT_ORDER,
    cuboid_keypoints,
    intrinsics_matrix,
    project_points,
    rotation_error_deg,
    scale_intrinsics,
)
from dope_hope.inference.predictor import DopePredictor
from dope_hope.io.meshes import sample_surface_points
from dope_hope.maps.targets import make_targets
from dope_hope.preprocess import IMAGENET_MEAN, IMAGENET_STD
from dope_hope.refine.depth import DepthImage
from dope_hope.refine.icp import IcpSettings, icp_refine
from dope_hope.refine.line_search import (
    auto_splat_px,
    depth_line_search,
    sample_depth,
    visible_points,
)
from dope_hope.render.box import box_surface_points, render_box_depth

sys.path.insert(0, str(Path(__file__).resolve().parent))
from official_dope import find_object_poses  # noqa: E402

STRIDE = 8
OBJECT = "Popcorn"
SIZE = get_object(OBJECT).size_array
CUBOID = cuboid_keypoints(SIZE)
K640 = intrinsics_matrix(615.0, 615.0, 319.5, 239.5)
K400 = scale_intrinsics(K640, 400 / 640, 400 / 480)
#: Keypoints stay this far inside the image, px (4 map cells: DOPE's sigma-3 smoothing
#: reflects at the border and pulls nearer peaks onto it).
MARGIN_PX = 32
#: name -> (image (H, W), belief noise std, affinity noise std, corner missing, overlapping pairs,
#: confused corners)
MAP_SETS = {
    "ideal, 80x60": ((480, 640), 0.0, 0.0, False, False, False),
    "noise 0.01 / 0.05": ((480, 640), 0.01, 0.05, False, False, False),
    "noise 0.03 / 0.1": ((480, 640), 0.03, 0.1, False, False, False),
    "noise 0.1 / 0.3": ((480, 640), 0.1, 0.3, False, False, False),
    "one corner missing per box": ((480, 640), 0.0, 0.0, True, False, False),
    "noise + missing corner + overlap": ((480, 640), 0.01, 0.05, True, True, False),
    "ideal, 400x400 input (50x50)": ((400, 400), 0.0, 0.0, False, False, False),
    "confused corners 0-2": ((480, 640), 0.0, 0.0, False, False, True),
}


def random_scene(rng: np.random.Generator, hw: tuple[int, int], K: np.ndarray, n: int = 10,
                 overlap: bool = False):
    """n random poses at 0.6-1.0 m whose keypoints lie at least :data:`MARGIN_PX` inside the
    image (rotation and depth redrawn until they do): centres on a jittered 4x3 grid, or
    (``overlap``) n/2 pairs on a 3x2 grid whose second box sits 7.5-12.5 % of the image width
    beside the first, 0.1 m nearer or farther (their cuboids overlap). Returns Rs, ts and the
    (n, 9, 2) keypoints, image px."""
    H, W = hw
    inner_w, inner_h = W - 2 * MARGIN_PX, H - 2 * MARGIN_PX
    centres = []
    if overlap:
        for s in rng.permutation(6)[: (n + 1) // 2]:
            u, v = MARGIN_PX + inner_w * (s % 3 + 0.5) / 3, MARGIN_PX + inner_h * (s // 3 + 0.5) / 2
            du = rng.choice([-1, 1]) * rng.uniform(0.075, 0.125) * W
            dv = rng.uniform(-0.025, 0.025) * H
            centres += [(u - du / 2, v - dv / 2, 0.0), (u + du / 2, v + dv / 2, rng.choice([-0.1, 0.1]))]
        centres = centres[:n]
    else:
        for s in rng.permutation(12)[:n]:
            u = MARGIN_PX + inner_w * (s % 4 + 0.5) / 4 + rng.uniform(-0.02, 0.02) * W
            v = MARGIN_PX + inner_h * (s // 4 + 0.5) / 3 + rng.uniform(-0.02, 0.02) * H
            centres.append((u, v, 0.0))
    Rs, ts, kps = [], [], []
    z_pair = 0.8
    for i, (u, v, dz) in enumerate(centres):
        while True:
            z = (z_pair + dz) if overlap and i % 2 else rng.uniform(0.6, 1.0)
            R = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
            t = np.linalg.inv(K) @ np.array([u, v, 1.0]) * z
            kp = project_points(CUBOID, K, R, t)
            if np.all((kp >= MARGIN_PX) & (kp <= np.array([W, H]) - 1 - MARGIN_PX)):
                break
        z_pair = z
        Rs.append(R); ts.append(t); kps.append(kp)
    return Rs, ts, np.stack(kps)


def confuse(belief: np.ndarray, affinity: np.ndarray, kp: np.ndarray, hw: tuple[int, int]):
    """Maps where corner maps 0, 1, 2 of every object also peak (1.0, the true peak lowered to
    0.7) on its corners 2, 3, 0, with fields there pointing at the object's centroid."""
    wrong = np.full_like(kp, np.nan)
    wrong[:, [0, 1, 2]] = kp[:, [2, 3, 0]]
    wrong[:, 8] = kp[:, 8]
    bw, aw = make_targets(wrong, hw, STRIDE)
    b, a = belief.copy(), affinity.copy()
    b[:3] = np.maximum(0.7 * belief[:3], bw[:3])
    ring = np.repeat(np.linalg.norm(aw[:6].reshape(3, 2, *aw.shape[1:]), axis=1) > 0, 2, axis=0)
    a[:6] = np.where(ring, aw[:6], affinity[:6])
    return b, a


def map_set(name: str, seed: int, n: int = 10):
    """One seeded scene of a map set: (belief, affinity, K, (H, W), Rs, ts)."""
    hw, sb, sa, missing, overlap, confused = MAP_SETS[name]
    rng = np.random.default_rng(seed)
    K = K640 if hw == (480, 640) else K400
    Rs, ts, kp = random_scene(rng, hw, K, n, overlap)
    drawn = kp.copy()
    if missing:
        drawn[np.arange(len(kp)), rng.integers(0, 8, len(kp))] = np.nan
    b, a = make_targets(drawn, hw, STRIDE)
    if confused:
        b, a = confuse(b, a, kp, hw)
    b = (b + rng.normal(0.0, sb, b.shape)).astype(np.float32) if sb else b
    a = (a + rng.normal(0.0, sa, a.shape)).astype(np.float32) if sa else a
    return b, a, K, hw, Rs, ts


class MapsOnly:
    """The model metadata a :class:`DopePredictor` needs; the bench hands it maps, so ``run``
    is never called."""

    stride = STRIDE
    class_name = OBJECT
    size_m = SIZE
    keypoint_order = KEYPOINT_ORDER
    frame = "mesh"
    mean, std = tuple(IMAGENET_MEAN), tuple(IMAGENET_STD)
    input_hw = None

    def run(self, batch):
        raise RuntimeError("the bench decodes given maps")


def found_boxes(poses, Rs, ts) -> int:
    """Boxes with a pose whose nine cuboid keypoints lie within 10 % of the cuboid diagonal of
    the truth on average (ADD on the keypoints); each pose counts for one box."""
    limit = 0.1 * float(np.linalg.norm(SIZE))
    truth = [CUBOID @ R.T + t for R, t in zip(Rs, ts)]
    free = set(range(len(truth)))
    for R, t in poses:
        pts = CUBOID @ np.asarray(R).T + np.asarray(t)
        add = {j: float(np.linalg.norm(pts - truth[j], axis=1).mean()) for j in free}
        j = min(add, key=add.get, default=None)
        if j is not None and add[j] < limit:
            free.discard(j)
    return len(truth) - len(free)


def maps_section(scenes: int, rounds: int, objects: int) -> None:
    """Official vs default vs groups on every map set (see the module docstring)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        _maps_table(scenes, rounds, objects)
    finally:
        torch.set_num_threads(threads)


#: The decoders compared besides the official one: name -> DopePredictor options.
ARMS = {"default": {"pose_search": "hypotheses"},
        "no floor": {"pose_search": "hypotheses", "decode": {"noise_sigmas": 0.0}},
        "groups": {"pose_search": "groups"}}


def _maps_table(scenes: int, rounds: int, objects: int) -> None:
    predictors = {}
    for hw in {v[0] for v in MAP_SETS.values()}:
        for arm, options in ARMS.items():
            p = DopePredictor(MapsOnly(), height=hw[0], **options)
            predictors[hw, arm] = (p, p.prepare(np.zeros(hw + (3,), np.uint8)))
    print(f"maps -> poses, {objects} boxes per image (one object's maps), {scenes} scenes x {rounds} rounds "
          f"per map set (interleaved; median CPU ms per image; found: mean boxes per image)")
    print(f"  {'map set':34s} {'official':>16s}" + "".join(f" {a:>16s}" for a in ARMS)
          + "   official/default  official/groups")

    def arm_run(arm, hw, b, a, K):
        p, net = predictors[hw, arm]
        return lambda: [(d.R, d.t) for d in p.detections_from_maps(b, a, net, K)]

    for name in MAP_SETS:
        times = {m: [] for m in ("official", *ARMS)}
        found = {m: [] for m in times}
        for s in range(scenes):
            b, a, K, hw, Rs, ts = map_set(name, 1000 + s, objects)
            bt, at = torch.from_numpy(b), torch.from_numpy(a)
            runs = {"official": lambda: find_object_poses(bt, at, CUBOID, K),
                    **{arm: arm_run(arm, hw, b, a, K) for arm in ARMS}}
            order = list(runs)
            for r in range(rounds):
                for m in order[r % len(order):] + order[: r % len(order)]:
                    t0 = time.process_time()
                    poses = runs[m]()
                    times[m].append(time.process_time() - t0)
                    if r == 0:
                        found[m].append(found_boxes(poses, Rs, ts))
        med = {m: 1000 * float(np.median(v)) for m, v in times.items()}
        cells = "".join(f" {med[m]:8.1f} / {np.mean(found[m]):4.1f}" for m in times)
        print(f"  {name:34s}{cells}   {med['official'] / med['default']:13.1f}x {med['official'] / med['groups']:15.1f}x")


def timed(fn, *args, repeats=3, **kwargs):
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn(*args, **kwargs)
        best = min(best, time.perf_counter() - t0)
    return best, out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", type=int, default=5, help="seeded scenes per map set")
    ap.add_argument("--rounds", type=int, default=5, help="timed rounds per scene and decoder")
    ap.add_argument("--objects", type=int, default=10, help="boxes per scene")
    ap.add_argument("--repeats", type=int, default=3, help="-LS and ICP: best of this many runs")
    only = ap.add_mutually_exclusive_group()
    only.add_argument("--only-maps", action="store_true", help="only the maps -> poses section")
    only.add_argument("--only-icp", action="store_true", help="only the -LS + ICP section")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    if args.only_icp:
        return icp_section(args.repeats)
    maps_section(args.scenes, args.rounds, args.objects)
    if args.only_maps:
        return 0
    ls_section(args.repeats)
    return icp_section(args.repeats)


def ls_section(repeats: int) -> None:
    """-LS per object against a dense grid search (see the module docstring)."""
    rng = np.random.default_rng(0)
    size = get_object("Cookies").size_array
    pts = box_surface_points(size)
    lo, hi = 0.8, 1.25
    dense = np.arange(lo, hi + 1e-9, 0.001)
    tl, tdn, el, edn = [], [], [], []
    for i in range(10):
        R = Rotation.random(random_state=100 + i).as_matrix()
        t = np.array([rng.uniform(-0.1, 0.1), rng.uniform(-0.06, 0.06), rng.uniform(0.5, 1.0)])
        depth = render_box_depth(size, R, t, K640, (480, 640))
        t0 = 1.1 * t
        dt, res = timed(depth_line_search, R, t0, pts, DepthImage.from_raw(depth, K640), repeats=repeats)
        tl.append(dt); el.append(1000 * np.linalg.norm(res.t - t))

        def dense_cost_only():
            # The same visibility pass and median cost, evaluated at every 0.1 % step.
            D = DepthImage.from_raw(depth, K640).metres
            A = pts @ R.T
            vis = visible_points(A + t0, K640, (480, 640), auto_splat_px(pts, K640, t0[2]), 0.005)
            A = A[vis]
            best, best_s = np.inf, 1.0
            for s in dense:
                X = A + s * t0
                uvw = X @ K640.T
                r = sample_depth(D, uvw[:, 0] / uvw[:, 2], uvw[:, 1] / uvw[:, 2]) - uvw[:, 2]
                c = np.median(np.abs(r[np.isfinite(r)]))
                if c < best:
                    best, best_s = c, s
            return best_s * t0

        dd, td = timed(dense_cost_only, repeats=1)
        tdn.append(dd); edn.append(1000 * np.linalg.norm(td - t))
    ml, md = 1000 * np.median(tl), 1000 * np.median(tdn)
    print(f"-LS per object (640x480 depth, {len(pts)} model points, start 10 % off along the ray):")
    print(f"  candidate (41-step grid + Brent): {ml:7.2f} ms   |t - t_true| median {np.median(el):.3f} mm, "
          f"max {np.max(el):.3f} mm")
    print(f"  baseline  (dense 0.1 % grid, {len(dense)} steps): {md:7.2f} ms   "
          f"median {np.median(edn):.3f} mm, max {np.max(edn):.3f} mm")
    print(f"  speed-up baseline/candidate: {md / ml:.1f}x")


def icp_section(repeats: int) -> int:
    """-LS + ICP per object: ten starts (default) vs one; see the module docstring."""
    import trimesh

    size = get_object("Ketchup").size_array  # bottle-sized box, three distinct extents
    pts = box_surface_points(size)
    icp_pts, icp_nrm = sample_surface_points(trimesh.creation.box(extents=size), 2000, oversample=10,
                                             return_normals=True)
    rng = np.random.default_rng(7)
    for kind in ("20 deg, random axis", "80 deg about the long axis"):
        rows = {"one start": [], "ten starts, all points": [], "ten starts, exact nearest": [],
                "ten starts (default)": []}
        for i in range(10):
            R = Rotation.random(random_state=200 + i).as_matrix()
            t = np.array([rng.uniform(-0.1, 0.1), rng.uniform(-0.06, 0.06), rng.uniform(0.5, 1.0)])
            depth = render_box_depth(size, R, t, K640, (480, 640))
            axis = rng.normal(size=3) if kind.startswith("20") else np.array([0.0, 1.0, 0.0])
            deg = 20.0 if kind.startswith("20") else 80.0
            R0 = R @ Rotation.from_rotvec(np.radians(deg) * axis / np.linalg.norm(axis)).as_matrix()
            ls = depth_line_search(R0, 1.1 * t, pts, DepthImage.from_raw(depth, K640))
            for name, kw in (("one start", {"start_rotations": ()}),
                             ("ten starts, all points", {"coarse_points": None}),
                             ("ten starts, exact nearest", {"nearest": "exact"}),
                             ("ten starts (default)", {})):
                dt, res = timed(icp_refine, R0, ls.t, icp_pts, icp_nrm, DepthImage.from_raw(depth, K640),
                                IcpSettings(**kw), repeats=repeats)
                ok = res.applied and rotation_error_deg(res.R, R) < 1.0 and np.linalg.norm(res.t - t) < 0.002
                rows[name].append((dt, ok))
        print(f"-LS + ICP per object (640x480 depth, 2000 model points; input {kind}, 10 % too far):")
        times = {}
        for name, r in rows.items():
            times[name] = 1000 * np.median([x[0] for x in r])
            print(f"  {name:26s} {times[name]:7.2f} ms   within 1 deg and 2 mm: {sum(x[1] for x in r)}/{len(r)}")
        print(f"  time ratio ten (all points) / ten (default, coarse phase on a thinned scene): "
              f"{times['ten starts, all points'] / times['ten starts (default)']:.1f}x; exact nearest / grid "
              f"{times['ten starts, exact nearest'] / times['ten starts (default)']:.1f}x; "
              f"ten (default) / one: {times['ten starts (default)'] / times['one start']:.1f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
