"""ADD-H time per pose at 500 points: dope_hope.evaluation.metrics.addh vs plain linear_sum_assignment.

Baseline: what the HOPE paper describes — scipy's ``linear_sum_assignment`` on the full
500 x 500 Euclidean distance matrix (``cdist``). Candidate:
:func:`dope_hope.evaluation.metrics.addh` (exact short-cuts from bounds and dual
certificates, then the same solver on a matrix reduced by dual potentials). Both run on the
same poses, one after the other, in this process; times are CPU time of the process (the
machine is shared). Every value is compared: how many are bitwise identical, and the
largest |difference|. Pose regimes, on HOPE-sized box, cylinder and bottle primitives:

* near: rotation <= 5°, translation <= 1 cm (a good detection);
* moderate: rotation <= 30°, translation <= 3 cm;
* far: uniform rotation, translation <= 10 cm (the metric simulation's regime);
* translation: pure translation <= 10 cm.

    python bench/addh_speed.py [--poses 20] [--seed 0]
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
from metric_simulation import hope_shape
from scipy.optimize import linear_sum_assignment
from scipy.spatial.distance import cdist
from scipy.spatial.transform import Rotation

from dope_hope.catalog import get_object
from dope_hope.evaluation import metrics
from dope_hope.io.meshes import sample_surface_points

REGIMES = {"near": (5.0, 0.01), "moderate": (30.0, 0.03), "far": (None, 0.10),
           "translation": (0.0, 0.10)}
OBJECTS = ("Milk", "Tuna", "Ketchup")  # a cuboid, a cylinder, a bottle


def random_pose(rng: np.random.Generator, max_deg: float | None, max_t: float):
    if max_deg is None:
        R = Rotation.random(random_state=rng).as_matrix()
    else:
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        R = Rotation.from_rotvec(np.radians(rng.uniform(0, max_deg)) * axis).as_matrix()
    u = rng.normal(size=3)
    return R, rng.uniform(0, max_t) * u / np.linalg.norm(u)


def baseline(R, t, pts) -> float:
    a, b = pts, pts @ R.T + t
    C = cdist(a, b)
    r, c = linear_sum_assignment(C)
    return float(C[r, c].mean())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--poses", type=int, default=20, help="poses per object and regime")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    clouds = {n: sample_surface_points(hope_shape(get_object(n).category, get_object(n).size_array), 500)
              for n in OBJECTS}
    I3, Z3 = np.eye(3), np.zeros(3)
    for R, t in (random_pose(rng, 30.0, 0.03), random_pose(rng, None, 0.1)):  # warm-up
        metrics.addh(R, t, I3, Z3, clouds["Milk"])
        baseline(R, t, clouds["Milk"])
    print(f"{'regime':<12} {'poses':>5} {'baseline ms':>12} {'addh ms':>9} {'speed-up':>9} "
          f"{'identical':>10} {'max |diff| m':>13}")
    all_b, all_c = [], []
    for regime, (max_deg, max_t) in REGIMES.items():
        tb, tc, diff, same = [], [], 0.0, 0
        for name in OBJECTS:
            pts = clouds[name]
            for _ in range(args.poses):
                R, t = random_pose(rng, max_deg, max_t)
                t0 = time.process_time()
                vb = baseline(R, t, pts)
                t1 = time.process_time()
                vc = metrics.addh(R, t, I3, Z3, pts)
                t2 = time.process_time()
                tb.append(t1 - t0)
                tc.append(t2 - t1)
                diff = max(diff, abs(vb - vc))
                same += vb == vc
        all_b += tb
        all_c += tc
        mb, mc = 1e3 * statistics.mean(tb), 1e3 * statistics.mean(tc)
        print(f"{regime:<12} {len(tb):>5} {mb:>12.2f} {mc:>9.2f} {mb / mc:>8.1f}x "
              f"{f'{same}/{len(tb)}':>10} {diff:>13.1e}")
    mb, mc = 1e3 * statistics.mean(all_b), 1e3 * statistics.mean(all_c)
    print(f"{'all':<12} {len(all_b):>5} {mb:>12.2f} {mc:>9.2f} {mb / mc:>8.1f}x")
    print("(mean CPU time per pose; both from the same point clouds and poses)")


if __name__ == "__main__":
    main()
