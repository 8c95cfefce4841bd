"""What a training run shows after each validation: ``results.png`` and the validation snapshot.

* :func:`plot_results`: the curves of ``metrics.csv`` (train loss and learning rate, validation
  loss and keypoint accuracy) over steps, one panel each, drawn as ultralytics draws its
  ``results.png``: the values with dots and a Gaussian-smoothed dotted line (sigma 3 points).
* :func:`snapshot_panel`: one row per validation image: the image with the ground-truth
  cuboid (white) and the decoded cuboids (colours), then the nine predicted belief maps
  (:func:`dope_hope.viz.belief_montage`).

matplotlib is used through its object API (``Figure`` + Agg canvas), never pyplot, so that
plotting touches no global backend state.
"""
from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter1d

from dope_hope.io.atomic import atomic_write_with
from dope_hope.maps.decode import DecodeSettings, decode_maps
from dope_hope.model.info import GROUP_BELIEF, group_channels
from dope_hope.viz import PALETTE, belief_montage, draw_cuboid, draw_label, montage

#: (event, column, panel title) of the results.png panels, in order.
PANELS = (
    ("train", "loss", "train/loss"),
    ("train", "lr", "train/lr"),
    ("val", "val_loss", "val/loss"),
    ("val", "val_kp_acc", "val/kp_acc (peaks)"),
    ("val", "val_kp_acc_decoded", "val/kp_acc (decoded)"),
)
#: Gaussian smoothing of the dotted line, points (ultralytics' plot_results uses 3).
SMOOTH_SIGMA = 3.0
#: Validation images in the snapshot.
SNAPSHOT_IMAGES = 3
#: Longer side of one snapshot tile, pixels.
SNAPSHOT_TILE = 192


def read_metrics(csv_path: str | Path) -> dict[tuple[str, str], tuple[np.ndarray, np.ndarray]]:
    """The (steps, values) of each (event, column) of a ``metrics.csv``, sorted by step.

    Empty and non-finite cells are skipped; where a step appears twice for one event (a run
    resumed from an earlier checkpoint) the later row wins.
    """
    series: dict[tuple[str, str], dict[int, float]] = {}
    with open(csv_path, newline="") as f:
        for row in csv.DictReader(f):
            event, step = row.get("event"), row.get("step")
            if not event or not step:
                continue
            for col, cell in row.items():
                if col in ("event", "step") or not cell:
                    continue
                try:
                    value = float(cell)
                except ValueError:
                    continue
                if math.isfinite(value):
                    series.setdefault((event, col), {})[int(float(step))] = value
    out = {}
    for key, by_step in series.items():
        steps = np.array(sorted(by_step), dtype=np.int64)
        out[key] = steps, np.array([by_step[s] for s in steps], dtype=np.float64)
    return out


def plot_results(csv_path: str | Path, png_path: str | Path) -> Path:
    """Draw the curves of ``csv_path`` (a run's metrics.csv) into ``png_path``, atomically.

    Panels: :data:`PANELS` (x: optimizer steps); a panel without values says "no values yet".
    Returns ``png_path``.
    """
    from matplotlib.figure import Figure  # noqa: PLC0415 (matplotlib (slow to import) only for results.png)

    data = read_metrics(csv_path)
    fig = Figure(figsize=(15, 3.2))
    axes = fig.subplots(1, len(PANELS))
    fig.subplots_adjust(left=0.04, right=0.99, bottom=0.16, top=0.9, wspace=0.3)  # "tight" costs a 2nd draw
    for ax, (event, col, title) in zip(axes, PANELS):
        ax.set_title(title, fontsize=11)
        ax.set_xlabel("step")
        if (event, col) not in data:
            ax.text(0.5, 0.5, "no values yet", ha="center", va="center", transform=ax.transAxes, color="gray")
            continue
        x, y = data[(event, col)]
        ax.plot(x, y, marker=".", linewidth=2, markersize=8, label="results")
        if len(y) > 3:
            ax.plot(x, gaussian_filter1d(y, sigma=SMOOTH_SIGMA, mode="nearest"), ":", linewidth=2, label="smooth")
        if col == "lr":
            ax.ticklabel_format(axis="y", style="sci", scilimits=(-2, 3))
    legend = next((ax for ax in axes if ax.get_legend_handles_labels()[0]), None)
    if legend is not None:  # (a legend without curves makes matplotlib warn on stderr)
        legend.legend(fontsize=8)
    png_path = Path(png_path)
    atomic_write_with(png_path, lambda tmp: fig.savefig(tmp, dpi=100))
    return png_path


@dataclass
class SnapshotItem:
    """One validation image and what the network predicted for it.

    rgb: (H, W, 3) uint8 network input (after the validation fit).
    belief: (9N, h, w) and affinity: (16N, h, w) maps of the last stage of a model of N
    objects, h = H / stride.
    gt_keypoints: (I, 9, 2) input pixels, NaN = absent (the dataset item's ``keypoints``).
    title: label drawn on the image (e.g. the frame's file name).
    object_names: the N objects' classes (empty for a one-object model).
    """

    rgb: np.ndarray
    belief: np.ndarray
    affinity: np.ndarray
    gt_keypoints: np.ndarray
    title: str = ""
    object_names: tuple[str, ...] = ()


def snapshot_panel(items: Sequence[SnapshotItem], stride: int, threshold: float,
                   tile: int = SNAPSHOT_TILE) -> np.ndarray:
    """One row per item: image + ground-truth (white) and decoded cuboids (two tiles high; with
    several objects one colour per object), then the 9 belief maps (two rows of tiles; with
    several objects each keypoint's maximum over the objects).

    Args:
        items: the validation images and their predicted maps.
        stride: map stride (input pixels per map cell).
        threshold: peak threshold of the decoder (the validation's ``val_peak_threshold``).
        tile: longer side of each tile, pixels.

    Returns:
        (H, W, 3) uint8 RGB.
    """

    if not items:
        raise ValueError("a snapshot of no images")
    settings = DecodeSettings(threshold=threshold)
    rows = []
    for item in items:
        img = item.rgb
        for kp in np.asarray(item.gt_keypoints, dtype=np.float64).reshape(-1, 9, 2):
            if np.isfinite(kp).any():
                img = draw_cuboid(img, kp, (255, 255, 255), draw_points=False)
        n_obj = max(1, len(item.object_names))
        maps_all = np.concatenate([item.belief, item.affinity], axis=0)
        counts = []
        for k in range(n_obj):
            group = maps_all[group_channels(k, n_obj)]
            instances = decode_maps(group[:GROUP_BELIEF], group[GROUP_BELIEF:], stride, settings)
            for n, inst in enumerate(instances):
                img = draw_cuboid(img, inst.keypoints, PALETTE[(k if n_obj > 1 else n) % len(PALETTE)])
            counts.append(len(instances))
        belief = item.belief.reshape(n_obj, GROUP_BELIEF, *item.belief.shape[1:]).max(axis=0)
        maps = belief_montage(belief, item.rgb, cols=5, max_side=tile)  # 2 rows: 5 + 4 maps
        th = maps.shape[0]
        tw = max(1, round(img.shape[1] * th / img.shape[0]))
        img = cv2.resize(img, (tw, th), interpolation=cv2.INTER_AREA)
        found = (", ".join(f"{name} {c}" for name, c in zip(item.object_names, counts) if c) or "0"
                 if n_obj > 1 else str(counts[0]))
        img = draw_label(img, f"{item.title} {found} decoded".strip())
        gap = np.full((th, 2, 3), 32, np.uint8)
        rows.append(np.concatenate([img, gap, maps], axis=1))
    width = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0)), constant_values=32) for r in rows]
    return montage(rows, cols=1)
