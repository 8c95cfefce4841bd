"""Draw the loop of `dope-hope adapt` (docs/commands/adapt_loop.png): frames, labels with the
depth as the teacher, carried labels, the mix with synthetic frames, fine-tuning, label again.

    python tools/adapt_loop_figure.py --out docs/commands/adapt_loop.png
"""
from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (after the headless backend is chosen)
from matplotlib.patches import FancyArrowPatch, FancyBboxPatch  # noqa: E402

#: (x, y, text, colour) of each box, axes units.
BOXES = {
    "frames": (0.10, 0.80, "unlabelled RGB-D frames\n(recording, video + depth,\nimage folder)", "#dbe9f6"),
    "model": (0.10, 0.40, "model\n(--weights, then\neach round's)", "#f6e3c8"),
    "detect": (0.40, 0.80, "detect with depth\n(-LS + ICP,\n3 working sizes)", "#e8e8e8"),
    "check": (0.70, 0.80, "depth confirms?\nsupport, residual,\nsilhouette on edges, score", "#d9f0d3"),
    "carry": (0.70, 0.47, "carry by the tracker\ninto missed frames,\nICP, confirm again", "#d9f0d3"),
    "labels": (0.95, 0.47, "labels\n(DOPE format,\nevidence)", "#fff2a8"),
    "mix": (0.70, 0.12, "mix with synthetic\nframes (ratio)", "#e8e8e8"),
    "train": (0.40, 0.12, "fine-tune\n(time budget,\nresumable)", "#f6e3c8"),
}
ARROWS = [("frames", "detect", ""), ("model", "detect", ""), ("detect", "check", ""),
          ("check", "labels", "kept"), ("check", "carry", ""), ("carry", "labels", "kept"),
          ("labels", "mix", ""), ("mix", "train", ""), ("train", "model", "next round")]


#: Half width and half height of a box, axes units.
HALF_W, HALF_H = 0.105, 0.09


def _edge(x: float, y: float, dx: float, dy: float) -> tuple[float, float]:
    """Where the ray from a box's centre (x, y) along (dx, dy) leaves the box."""
    scale = min(HALF_W / abs(dx) if dx else float("inf"), HALF_H / abs(dy) if dy else float("inf"))
    return x + dx * scale, y + dy * scale


def draw(out: Path) -> Path:
    """Write the figure to ``out`` (PNG); returns it."""
    fig, ax = plt.subplots(figsize=(9.0, 4.6), dpi=100)
    ax.set_xlim(-0.05, 1.1)
    ax.set_ylim(-0.05, 1.0)
    ax.axis("off")
    for x, y, text, colour in BOXES.values():
        ax.add_patch(FancyBboxPatch((x - HALF_W, y - HALF_H), 2 * HALF_W, 2 * HALF_H, boxstyle="round,pad=0.01",
                                    fc=colour, ec="#555555"))
        ax.text(x, y, text, ha="center", va="center", fontsize=8)
    for a, b, label in ARROWS:
        (xa, ya, *_), (xb, yb, *_) = BOXES[a], BOXES[b]
        start = _edge(xa, ya, xb - xa, yb - ya)
        end = _edge(xb, yb, xa - xb, ya - yb)
        ax.add_patch(FancyArrowPatch(start, end, arrowstyle="-|>", mutation_scale=12, color="#333333",
                                     shrinkA=4, shrinkB=4))
        if label:
            ax.text((xa + xb) / 2, (ya + yb) / 2 + 0.03, label, ha="center", fontsize=7, color="#225522")
    ax.set_title("dope-hope adapt: a model taught by its own depth-confirmed labels", fontsize=10)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent.parent / "docs" / "commands"
                        / "adapt_loop.png")
    print(draw(parser.parse_args().out))


if __name__ == "__main__":
    main()
