"""Post-processing speed: decode + PnP per image, and the depth line search (-LS) per object.

Candidate: ``dope_hope.maps.decode.decode_maps`` (vectorized peaks, log-parabola refinement,
one-to-one assignment) + ``dope_hope.inference.pnp.solve_pnp`` (PnP-RANSAC + LM).
Baseline: an official-DOPE-style decoder written here for comparison (a Python loop per
peak over an 11x11 weighted-average window, Python loops over corner candidates x
centroids for the affinity test, only complete 9-point objects) + ``cv2.solvePnP``
(SOLVEPNP_ITERATIVE) on the nine points, as DOPE does.
Both see the same maps: targets of 10 random poses, 50x50 maps (stride 8) of a 400x400 input.

Pose search: the predictor's default, ``decode.corner_candidates`` (every feasible peak, up to
3 per corner type) + ``pose.solve_pnp_candidates`` (multi-hypothesis PnP), against the
candidate above (one corner per type), on the same maps and on "confused" maps where corner
maps 0-2 of every object also carry a stronger peak on corners 2, 3, 0 (a trained lite net's
commonest error): the search's price in time and what it buys in objects found.

-LS: ``depth_line_search`` (coarse 41-step grid + bounded Brent) against a dense grid search
over the same range in 0.1 % steps (the simple way to do it), same cost function, 640x480
depth of a ray-cast box, ~4200 surface points.

-LS + ICP: ``dope_hope.refine.icp.icp_refine`` with its ten starts (the default: a coarse phase on a
thinned scene, four finish) against the same ten starts all on every point (the baseline) and
against one start, after the line search, per object: the box's depth as above, the input pose turned 20 deg
(random axis) or 80 deg (about the box's long axis: a lite net's commonest rotation error)
and 10 % too far; time, and how often each ends within 1 deg and 2 mm.

    python bench/postprocess.py [--images 20] [--repeats 3] [--only-icp]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter
from scipy.spatial.transform import Rotation

from dope_hope.catalog import get_object
from dope_hope.geometry import (
    cuboid_keypoints,
    intrinsics_matrix,
    project_points,
    rotation_error_deg,
    scale_intrinsics,
)
from dope_hope.inference.pnp import solve_pnp, solve_pnp_candidates
from dope_hope.io.meshes import sample_surface_points
from dope_hope.maps.decode import corner_candidates, decode_maps
from dope_hope.maps.grid import map_to_image
from dope_hope.maps.targets import make_targets
from dope_hope.refine.depth import DepthImage
from dope_hope.refine.icp import icp_refine
from dope_hope.refine.line_search import (
    _sample_depth,
    auto_splat_px,
    depth_line_search,
    visible_points,
)

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # the tests' box helpers (one definition)
from box_depth import box_surface_points, render_box_depth  # noqa: E402

STRIDE = 8
HW = (400, 400)
K400 = scale_intrinsics(intrinsics_matrix(615.0, 615.0, 319.5, 239.5), 400 / 640, 400 / 480)
CUBOID = cuboid_keypoints(get_object("Popcorn").size_array)


def random_scene(rng: np.random.Generator, n: int = 10):
    """n random poses on a jittered 4x3 grid at 0.6-1.0 m, all inside the 400x400 view."""
    slots = rng.permutation(12)[:n]
    Rs, ts = [], []
    for s in slots:
        gx, gy = s % 4, s // 4
        z = rng.uniform(0.6, 1.0)
        u = 50 + gx * 100 + rng.uniform(-10, 10)
        v = 70 + gy * 130 + rng.uniform(-10, 10)
        ray = np.linalg.inv(K400) @ np.array([u, v, 1.0])
        Rs.append(Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix())
        ts.append(ray * z)
    kp = np.stack([project_points(CUBOID, K400, R, t) for R, t in zip(Rs, ts)])
    return Rs, ts, kp


# ------------------------------------------------------------------ DOPE-style baseline
def dope_style_decode(belief, affinity, stride, smooth_sigma=1.0, thresh_map=0.01,
                      thresh_points=0.1, thresh_angle=0.5, win=11):
    """Official-DOPE-style decoding with per-peak Python loops (baseline only)."""
    all_peaks = []
    for j in range(belief.shape[0]):
        raw = belief[j]
        m = gaussian_filter(raw, sigma=smooth_sigma)
        left = np.zeros_like(m); left[1:, :] = m[:-1, :]
        right = np.zeros_like(m); right[:-1, :] = m[1:, :]
        up = np.zeros_like(m); up[:, 1:] = m[:, :-1]
        down = np.zeros_like(m); down[:, :-1] = m[:, 1:]
        binary = (m >= left) & (m >= right) & (m >= up) & (m >= down) & (m > thresh_map)
        ys, xs = np.nonzero(binary)
        peaks = []
        r = win // 2
        for x, y in zip(xs, ys):
            wsum = sx = sy = 0.0
            for dy in range(-r, r + 1):
                for dx in range(-r, r + 1):
                    yy, xx = y + dy, x + dx
                    if 0 <= yy < raw.shape[0] and 0 <= xx < raw.shape[1]:
                        w = float(raw[yy, xx])
                        wsum += w; sx += w * xx; sy += w * yy
            px, py = (sx / wsum, sy / wsum) if wsum > 0 else (float(x), float(y))
            peaks.append((px, py, float(raw[y, x])))
        all_peaks.append(peaks)
    objects = [[(p[0], p[1]), [None] * 8, [None] * 8] for p in all_peaks[-1] if p[2] > thresh_points]
    for k in range(8):
        for cx, cy, score in all_peaks[k]:
            if score < thresh_points:
                continue
            best, best_dist = -1, 1e9
            for i, obj in enumerate(objects):
                ox, oy = obj[0]
                ix, iy = int(round(cx)), int(round(cy))  # DOPE truncates; rounding is fairer here
                v = np.array([affinity[2 * k, iy, ix], affinity[2 * k + 1, iy, ix]]) * 10
                v = v / (np.linalg.norm(v) + 1e-12)
                c = np.array([ox - cx, oy - cy])
                dist = float(np.linalg.norm(c))
                c = c / (dist + 1e-12)
                if np.linalg.norm(c - v) < thresh_angle and dist < best_dist:
                    best, best_dist = i, dist
            if best >= 0 and (objects[best][2][k] is None or best_dist < objects[best][2][k]):
                objects[best][1][k] = (cx, cy)
                objects[best][2][k] = best_dist
    out = []
    for obj in objects:
        if any(p is None for p in obj[1]):
            continue  # DOPE drops incomplete cuboids
        pts = np.array(obj[1] + [obj[0]], dtype=np.float64)
        out.append(map_to_image(pts, stride))
    return out


def baseline_image(belief, affinity, K):
    poses = []
    for kp in dope_style_decode(belief, affinity, STRIDE):
        ok, rvec, tvec = cv2.solvePnP(CUBOID, kp, K, np.zeros(5), flags=cv2.SOLVEPNP_ITERATIVE)
        if ok:
            poses.append((cv2.Rodrigues(rvec)[0], tvec.ravel()))
    return poses


def candidate_image(belief, affinity, K):
    poses = []
    for inst in decode_maps(belief, affinity, STRIDE):
        p = solve_pnp(inst.keypoints, inst.scores, CUBOID, K)
        if p is not None:
            poses.append((p.R, p.t))
    return poses


def search_image(belief, affinity, K):
    poses = []
    for c in corner_candidates(belief, affinity, STRIDE):
        p = solve_pnp_candidates(c.keypoint_ids, c.xy, c.scores, CUBOID, K)
        if p is not None:
            poses.append((p.R, p.t))
    return poses


def confuse(belief: np.ndarray, affinity: np.ndarray, kp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Maps where corner maps 0, 1, 2 of every object also peak (1.0, the true peak lowered to
    0.7) on its corners 2, 3, 0, with fields there pointing at the object's centroid."""
    wrong = np.full_like(kp, np.nan)
    wrong[:, [0, 1, 2]] = kp[:, [2, 3, 0]]
    wrong[:, 8] = kp[:, 8]
    bw, aw = make_targets(wrong, HW, STRIDE)
    b, a = belief.copy(), affinity.copy()
    b[:3] = np.maximum(0.7 * belief[:3], bw[:3])
    ring = np.repeat(np.linalg.norm(aw[:6].reshape(3, 2, *aw.shape[1:]), axis=1) > 0, 2, axis=0)
    a[:6] = np.where(ring, aw[:6], affinity[:6])
    return b, a


def accuracy(poses, Rs, ts):
    """(found, median rotation error deg, median translation error mm) vs ground truth."""
    rot, tra, found = [], [], set()
    for R, t in poses:
        j = int(np.argmin([np.linalg.norm(t - tt) for tt in ts]))
        if np.linalg.norm(t - ts[j]) < 0.05:
            found.add(j)
            rot.append(rotation_error_deg(R, Rs[j]))
            tra.append(1000 * np.linalg.norm(t - ts[j]))
    return len(found), float(np.median(rot)) if rot else np.nan, float(np.median(tra)) if tra else np.nan


def timed(fn, *args, repeats=3, **kwargs):
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn(*args, **kwargs)
        best = min(best, time.perf_counter() - t0)
    return best, out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--images", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--objects", type=int, default=10)
    ap.add_argument("--only-icp", action="store_true", help="only the -LS + ICP section")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    if args.only_icp:
        return icp_section(args.repeats)
    rng = np.random.default_rng(0)

    t_cand, t_base, acc_c, acc_b = [], [], [], []
    for _ in range(args.images):
        Rs, ts, kp = random_scene(rng, args.objects)
        b, a = make_targets(kp, HW, STRIDE)
        tc, pc = timed(candidate_image, b, a, K400, repeats=args.repeats)
        tb, pb = timed(baseline_image, b, a, K400, repeats=args.repeats)
        t_cand.append(tc); t_base.append(tb)
        acc_c.append(accuracy(pc, Rs, ts)); acc_b.append(accuracy(pb, Rs, ts))
    ac, ab = np.array(acc_c), np.array(acc_b)
    mc, mb = 1000 * np.median(t_cand), 1000 * np.median(t_base)
    print(f"decode + PnP, {args.objects} objects, 50x50 maps (400x400 input), "
          f"{args.images} images, median of best-of-{args.repeats}:")
    print(f"  candidate (vectorized + RANSAC/LM): {mc:7.2f} ms/image   found {ac[:, 0].mean():.2f}/"
          f"{args.objects}   rot {np.nanmedian(ac[:, 1]):.4f} deg   t {np.nanmedian(ac[:, 2]):.3f} mm")
    print(f"  baseline  (DOPE-style loops + PnP): {mb:7.2f} ms/image   found {ab[:, 0].mean():.2f}/"
          f"{args.objects}   rot {np.nanmedian(ab[:, 1]):.4f} deg   t {np.nanmedian(ab[:, 2]):.3f} mm")
    print(f"  speed-up baseline/candidate: {mb / mc:.1f}x")

    # Pose search vs one corner per type, on clean and on confused maps.
    rng_s = np.random.default_rng(1)
    for kind in ("clean", "confused"):
        t_grp, t_srch, f_grp, f_srch = [], [], [], []
        for _ in range(args.images):
            Rs, ts, kp = random_scene(rng_s, args.objects)
            b, a = make_targets(kp, HW, STRIDE)
            if kind == "confused":
                b, a = confuse(b, a, kp)
            tg, pg = timed(candidate_image, b, a, K400, repeats=args.repeats)
            tsr, ps = timed(search_image, b, a, K400, repeats=args.repeats)
            t_grp.append(tg); t_srch.append(tsr)
            f_grp.append(accuracy(pg, Rs, ts)[0]); f_srch.append(accuracy(ps, Rs, ts)[0])
        mg, ms_ = 1000 * np.median(t_grp), 1000 * np.median(t_srch)
        print(f"pose search, {kind} maps ({args.objects} objects, {args.images} images):")
        print(f"  one corner per type (decode_maps + solve_pnp):               {mg:7.2f} ms/image   "
              f"found {np.mean(f_grp):.2f}/{args.objects}")
        print(f"  search (corner_candidates + solve_pnp_candidates, default):  {ms_:7.2f} ms/image   "
              f"found {np.mean(f_srch):.2f}/{args.objects}")
        print(f"  time ratio search/one-per-type: {ms_ / mg:.1f}x")

    # -LS per object
    K640 = intrinsics_matrix(615.0, 615.0, 319.5, 239.5)
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
        dt, res = timed(depth_line_search, R, t0, pts, DepthImage.from_raw(depth, K640), repeats=args.repeats)
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
                r = _sample_depth(D, uvw[:, 0] / uvw[:, 2], uvw[:, 1] / uvw[:, 2]) - uvw[:, 2]
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
    return icp_section(args.repeats)


def icp_section(repeats: int) -> int:
    """-LS + ICP per object: ten starts (default) vs one; see the module docstring."""
    import trimesh

    K640 = intrinsics_matrix(615.0, 615.0, 319.5, 239.5)
    size = get_object("Ketchup").size_array  # bottle-sized box, three distinct extents
    pts = box_surface_points(size)
    icp_pts, icp_nrm = sample_surface_points(trimesh.creation.box(extents=size), 2000, oversample=10,
                                             return_normals=True)
    rng = np.random.default_rng(7)
    for kind in ("20 deg, random axis", "80 deg about the long axis"):
        rows = {"one start": [], "ten starts, all points": [], "ten starts (default)": []}
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
                             ("ten starts (default)", {})):
                dt, res = timed(icp_refine, R0, ls.t, icp_pts, icp_nrm, DepthImage.from_raw(depth, K640), repeats=repeats, **kw)
                ok = res.applied and rotation_error_deg(res.R, R) < 1.0 and np.linalg.norm(res.t - t) < 0.002
                rows[name].append((dt, ok))
        print(f"-LS + ICP per object (640x480 depth, 2000 model points; input {kind}, 10 % too far):")
        times = {}
        for name, r in rows.items():
            times[name] = 1000 * np.median([x[0] for x in r])
            print(f"  {name:22s} {times[name]:7.2f} ms   within 1 deg and 2 mm: {sum(x[1] for x in r)}/{len(r)}")
        print(f"  time ratio ten (all points) / ten (default, coarse phase on a thinned scene): "
              f"{times['ten starts, all points'] / times['ten starts (default)']:.1f}x; "
              f"ten (default) / one: {times['ten starts (default)'] / times['one start']:.1f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
