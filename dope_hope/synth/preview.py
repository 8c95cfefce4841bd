"""``preview.png`` of a synthetic dataset: written frames read back from disk with their
projected cuboids."""
from __future__ import annotations

import os
from pathlib import Path

from dope_hope.io.dope_json import read_dope_json
from dope_hope.io.images import read_rgb, write_rgb
from dope_hope.synth.writer import frame_paths
from dope_hope.viz import PALETTE, draw_cuboid, draw_label, montage


def write_preview(out_dir: str | os.PathLike, indices: list[int], max_frames: int = 16) -> Path | None:
    """``preview.png``: a montage of up to ``max_frames`` written frames with their projected
    cuboids (read back from disk, so it also checks what was written)."""
    tiles = []
    for i in sorted(indices)[:max_frames]:
        paths = frame_paths(out_dir, i)
        if not paths["json"].is_file():
            continue
        frame = read_dope_json(paths["json"])
        img = read_rgb(paths["rgb"])
        for k, obj in enumerate(frame.objects):
            if obj.projected_cuboid is not None:
                img = draw_cuboid(img, obj.projected_cuboid, PALETTE[k % len(PALETTE)])
        vis = " ".join(f"{o.visibility:.2f}" for o in frame.objects if o.visibility is not None)
        tiles.append(draw_label(img, f"{i:06d} vis {vis}"))
    if not tiles:
        return None
    path = Path(out_dir) / "preview.png"
    write_rgb(path, montage(tiles, cols=min(4, len(tiles))))
    return path
