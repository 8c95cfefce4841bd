"""The demo's ONNX model: exported once beside the demo's output, reused while the weights are
unchanged."""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

from dope_hope.export.pipeline import export_checkpoint
from dope_hope.export.to_onnx import ExportSettings
from dope_hope.io.atomic import atomic_write_text
from dope_hope.version import __version__


def file_sha256(path: Path) -> str:
    """Hex SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def ensure_onnx(weights: Path, out_dir: Path, input_hw: tuple[int, int]) -> tuple[Path, bool]:
    """Export ``weights`` to ``out_dir/<stem>.onnx`` at the fixed input (H, W) unless an export
    of the same weights (SHA-256) at that size is already there. Returns (path, exported)."""
    onnx_path = out_dir / f"{weights.stem}.onnx"
    stamp_path = out_dir / f"{weights.stem}.onnx.json"
    stamp = {"weights_sha256": file_sha256(weights), "input_hw": [int(v) for v in input_hw],
             "dope_hope_version": __version__}
    if onnx_path.is_file() and stamp_path.is_file():
        try:
            if json.loads(stamp_path.read_text(encoding="utf-8")) == stamp:
                return onnx_path, False
        except (OSError, json.JSONDecodeError):
            pass
    export_checkpoint(weights, onnx_path, ExportSettings(input_hw=(int(input_hw[0]), int(input_hw[1]))))
    atomic_write_text(stamp_path, json.dumps(stamp, indent=1) + "\n")
    return onnx_path, True
