"""Does the lite network learn corner identity on CPU? lite vs a plain narrow net, same budget.

A toy task with the real targets: a box with six differently coloured faces (one fixed
"object"), random pose and size, over clutter, 200x200; belief/affinity targets from
``dope_hope.maps.targets`` at stride 8. Each network trains for the same wall-clock budget on
``--threads`` threads (AdamW, lr 2e-3, batch 16, per-stage MSE summed, as configs/lite.yaml),
then is scored on held-out images: the fraction of the 9 keypoints whose last-stage belief
peak (3x3 weighted sub-cell refinement) lies within 5 px, and the fraction that land within
5 px of a *different* keypoint of the box (a corner-identity mix-up).

    python bench/lite_toy.py [--minutes 4] [--threads 1] [--eval-every 2] [--only lite|plain]

The baseline is the kind of net the lite design is meant to beat: a plain stack of
BatchNorm 3x3 convs to stride 8 (receptive field ~90 px), no context path, one stage.
"""
from __future__ import annotations

import argparse
import time

import cv2
import numpy as np
import torch
from scipy.spatial.transform import Rotation
from torch import nn

from dope_hope.geometry import CUBOID_CORNER_SIGNS, cuboid_keypoints, project_points
from dope_hope.maps.grid import map_to_image
from dope_hope.maps.targets import make_targets
from dope_hope.model import build_model, normalize_batch
from dope_hope.model.lite import conv_bn_relu

SIZE = 200
STRIDE = 8
K = np.array([[220.0, 0, 99.5], [0, 220.0, 99.5], [0, 0, 1]])
FACE_COLOURS = [(220, 40, 40), (40, 180, 60), (40, 70, 220), (230, 200, 40), (200, 60, 200), (40, 200, 210)]


def render(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(200, 200, 3) uint8 image, (9, 2) keypoints in pixels."""
    low = rng.integers(0, 256, (6, 6, 3)).astype(np.uint8)
    img = cv2.resize(low, (SIZE, SIZE), interpolation=cv2.INTER_CUBIC)
    for _ in range(rng.integers(2, 6)):  # clutter
        x, y = rng.integers(0, SIZE, 2)
        w, h = rng.integers(10, 60, 2)
        cv2.rectangle(img, (int(x), int(y)), (int(x + w), int(y + h)), tuple(int(c) for c in rng.integers(0, 256, 3)), -1)
    size = rng.uniform([0.05, 0.10, 0.04], [0.09, 0.20, 0.08])
    R = Rotation.random(random_state=int(rng.integers(2**31))).as_matrix()
    t = np.array([rng.uniform(-0.06, 0.06), rng.uniform(-0.06, 0.06), rng.uniform(0.35, 0.6)])
    kp = project_points(cuboid_keypoints(size), K, R, t)
    corners = CUBOID_CORNER_SIGNS * size / 2
    for axis in range(3):
        for sign in (1, -1):
            normal = np.zeros(3)
            normal[axis] = sign
            centre = R @ (normal * size / 2) + t
            if np.dot(R @ normal, centre) >= 0:
                continue  # back face
            idx = np.flatnonzero(CUBOID_CORNER_SIGNS[:, axis] == sign)
            pts = project_points(corners[idx], K, R, t).astype(np.float32)
            hull = cv2.convexHull(pts).round().astype(np.int32)
            shade = 0.6 + 0.4 * abs(float((R @ normal)[2]))
            colour = tuple(int(c * shade) for c in FACE_COLOURS[2 * axis + (sign < 0)])
            cv2.fillConvexPoly(img, hull, colour, lineType=cv2.LINE_AA)
    img = np.clip(img.astype(np.float32) + rng.normal(0, 4, img.shape), 0, 255).astype(np.uint8)
    return img, kp


def make_set(n: int, seed: int):
    rng = np.random.default_rng(seed)
    imgs, beliefs, affs, kps = [], [], [], []
    for _ in range(n):
        img, kp = render(rng)
        b, a = make_targets(kp[None], (SIZE, SIZE), STRIDE, 1.0, 1.0)
        imgs.append(img)
        beliefs.append(b)
        affs.append(a)
        kps.append(kp)
    x = normalize_batch(torch.from_numpy(np.stack(imgs)).permute(0, 3, 1, 2))
    return x, torch.from_numpy(np.stack(beliefs)), torch.from_numpy(np.stack(affs)), np.stack(kps)


class PlainNet(nn.Module):
    """Baseline: a plain BN conv stack to stride 8, one stage, same outputs."""

    def __init__(self, w: int = 48):
        super().__init__()
        self.body = nn.Sequential(
            conv_bn_relu(3, w // 2, 2), conv_bn_relu(w // 2, w, 2), conv_bn_relu(w, w),
            conv_bn_relu(w, 2 * w, 2), *[conv_bn_relu(2 * w, 2 * w) for _ in range(4)],
            nn.Conv2d(2 * w, 25, 1))
        self.stride = 8

    def forward(self, x):
        m = self.body(x)
        return [(m[:, :9], m[:, 9:])]


def peaks(belief: np.ndarray) -> np.ndarray:
    """(9, h, w) -> (9, 2) image px of each map's maximum, 3x3 weighted sub-cell refinement."""
    k, h, w = belief.shape
    out = np.zeros((k, 2))
    for c in range(k):
        y, x = np.unravel_index(np.argmax(belief[c]), (h, w))
        y0, y1, x0, x1 = max(y - 1, 0), min(y + 2, h), max(x - 1, 0), min(x + 2, w)
        patch = np.clip(belief[c, y0:y1, x0:x1], 0, None)
        yy, xx = np.mgrid[y0:y1, x0:x1]
        s = patch.sum()
        out[c] = ((xx * patch).sum() / s, (yy * patch).sum() / s) if s > 0 else (x, y)
    return map_to_image(out, STRIDE)


def train_and_score(model: nn.Module, data, val, seconds: float, eval_every: float = 0.0,
                    name: str = "") -> dict[str, float]:
    """Train for ``seconds`` of wall clock (eval time excluded); score on ``val``."""
    x, b, a, _ = data
    opt = torch.optim.AdamW(model.parameters(), lr=2e-3, weight_decay=1e-4)
    rng = np.random.default_rng(0)
    steps, trained, next_eval = 0, 0.0, eval_every or np.inf
    while trained < seconds:
        model.train()
        t0 = time.perf_counter()
        idx = torch.from_numpy(rng.choice(len(x), 16, replace=False))
        out = model(x[idx])
        loss = sum(((pb - b[idx]) ** 2).mean() + ((pa - a[idx]) ** 2).mean() for pb, pa in out)
        opt.zero_grad()
        loss.backward()
        opt.step()
        steps += 1
        trained += time.perf_counter() - t0
        if trained >= next_eval and trained < seconds:
            r = score(model, val)
            print(f"  {name} {trained / 60:5.1f} min, step {steps:5d}: within 5 px "
                  f"{100 * r['within_5px']:5.1f} %, mix-ups {100 * r['corner_mixup']:5.1f} %", flush=True)
            next_eval += eval_every
    r = score(model, val)
    r.update(steps=steps, loss=loss.item())
    return r


def score(model: nn.Module, val) -> dict[str, float]:
    model.eval()
    vx, _, _, vk = val
    with torch.no_grad():
        beliefs = torch.cat([model(vx[i:i + 32])[-1][0] for i in range(0, len(vx), 32)]).numpy()
    pred = np.stack([peaks(bm) for bm in beliefs])                    # (N, 9, 2)
    d = np.linalg.norm(pred[:, :, None] - vk[:, None], axis=-1)        # (N, 9 pred, 9 gt)
    inside = ((vk >= 0) & (vk <= SIZE - 1)).all(-1)                    # keypoints in the image
    own = np.einsum("nkk->nk", d)
    other = np.where(np.eye(9, dtype=bool)[None], np.inf, d).min(-1)
    return {"within_5px": float((own[inside] <= 5).mean()),
            "corner_mixup": float(((other <= 5) & (own > 5))[inside].mean())}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--minutes", type=float, default=4.0)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--train", type=int, default=3000)
    p.add_argument("--eval-every", type=float, default=0.0, help="minutes between interim scores")
    p.add_argument("--only", choices=("plain", "lite"), default=None, help="run one model")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    t0 = time.perf_counter()
    data, val = make_set(args.train, 1), make_set(300, 2)
    print(f"toy data: {args.train} train / 300 val images in {time.perf_counter() - t0:.0f} s; "
          f"{args.minutes} min per model on {args.threads} thread(s)")
    results = {}
    models = {"plain": PlainNet, "lite": lambda: build_model({"arch": "lite", "head": 50, "stages": 2})}
    for name, make in models.items():
        if args.only and name != args.only:
            continue
        model = make()
        n = sum(q.numel() for q in model.parameters())
        r = train_and_score(model, data, val, args.minutes * 60, args.eval_every * 60, name)
        results[name] = r
        print(f"{name:6s} {n / 1e6:.2f} M params  steps {r['steps']:5d}  loss {r['loss']:.4f}  "
              f"within 5 px {100 * r['within_5px']:5.1f} %  corner mix-ups {100 * r['corner_mixup']:5.1f} %")
    if len(results) < 2:
        return
    print(f"lite / plain, keypoints within 5 px: "
          f"{results['lite']['within_5px'] / max(results['plain']['within_5px'], 1e-9):.2f}x")


if __name__ == "__main__":
    main()
