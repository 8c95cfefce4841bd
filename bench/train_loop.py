"""The training loop's speed: crops per second of `dope-hope train` on real frames, candidate
and baseline side by side.

`bench/train_throughput.py` times the optimizer step alone on one batch; this times what a
training run does between two logged steps: reading and decoding frames, augmenting them,
drawing their targets, the step itself, the logging. Each arm is a fresh `dope-hope train
--config lite` run from the shipped start, one after the other on the same cores, on the first
``--frames`` frames of ``--data`` (linked into a temporary folder: a few epochs pass in
minutes, so the figure is the steady state of a long run, whose later epochs read the frames
the first one decoded); validation is off. It prints each arm's median crops/s over the
logged windows after ``--skip-steps`` (default: the first epoch and 20 steps) and the ratio
candidate / baseline.

The candidate is this checkout with ``--set``; the baseline is ``--baseline-tree`` (a checkout
of another commit, e.g. ``git worktree add --detach ../base <commit>``; default this checkout)
with ``--baseline-set``:

    python bench/train_loop.py --data runs/e2e/train --object Ketchup --baseline-tree ../base
    python bench/train_loop.py --data runs/e2e/train --object Ketchup \\
        --baseline-set train.frame_cache_mb=0 train.workers=1       # one setting against another
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from dope_hope.devices import cpu_line  # noqa: E402
from dope_hope.errors import DopeHopeError  # noqa: E402
from dope_hope.io.dope_json import find_image, list_dope_frames  # noqa: E402


def link_frames(data: Path, count: int, out: Path) -> int:
    """Link the first ``count`` frames (JSON + image) of ``data`` into ``out``; the number linked."""
    out.mkdir(parents=True, exist_ok=True)
    frames = list_dope_frames(data)[:count]
    for json_path in frames:
        for src in (json_path, find_image(json_path)):
            (out / src.name).symlink_to(src.resolve())
    return len(frames)


def run_arm(tree: Path, data: Path, args: argparse.Namespace, overrides: list[str], out: Path) -> list[dict]:
    """One `dope-hope train` run from ``tree``; its logged training rows."""
    mesh = ["--mesh", str(args.mesh)] if args.mesh else []
    cmd = [sys.executable, "-m", "dope_hope", "train", "--config", "lite", "--data", str(data),
           "--object", args.object, *mesh, "--out", str(out), "--time-budget", str(args.minutes),
           "--no-progress", "--init", "pretrained", "--set", "train.val_every=0", "train.plots=false",
           *overrides]
    env = dict(os.environ, PYTHONPATH=str(tree))
    done = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"{tree}: dope-hope train failed ({done.returncode}): "
                         f"{(done.stderr.strip().splitlines() or ['no output'])[-1]}")
    rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines() if line.strip()]
    return [r for r in rows if r.get("event") == "train"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, required=True, help="a DOPE-format folder of training frames")
    ap.add_argument("--object", required=True, help="the class to train (its frames' class name)")
    ap.add_argument("--mesh", type=Path, help="its mesh (`dope-hope train --mesh`), for symmetric labels")
    ap.add_argument("--frames", type=int, default=2000, help="frames used (default 2000)")
    ap.add_argument("--minutes", type=float, default=2.0, help="each arm's time budget (default 2)")
    ap.add_argument("--skip-steps", type=int, help="steps not measured (default: one epoch + 20)")
    ap.add_argument("--set", nargs="+", default=[], metavar="KEY=VALUE", help="the candidate's overrides")
    ap.add_argument("--baseline-tree", type=Path, default=REPO, help="the baseline's checkout (default this one)")
    ap.add_argument("--baseline-set", nargs="+", default=[], metavar="KEY=VALUE",
                    help="the baseline's overrides")
    args = ap.parse_args()
    if not (args.baseline_tree / "dope_hope" / "__init__.py").is_file():
        ap.error(f"--baseline-tree {args.baseline_tree}: not a dope-hope checkout (no dope_hope/__init__.py)")
    if args.frames < 64 or args.minutes <= 0:
        ap.error("--frames must be >= 64 and --minutes > 0")
    print(cpu_line())
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / "frames"
        try:
            n = link_frames(args.data, args.frames, data)
        except DopeHopeError as exc:
            ap.error(f"--data: {exc}")
        if n < 64:
            ap.error(f"--data {args.data}: {n} frames, need at least 64")
        skip = args.skip_steps if args.skip_steps is not None else n // 16 + 20
        rates = {}
        for name, tree, overrides in (("baseline", args.baseline_tree, args.baseline_set),
                                      ("candidate", REPO, args.set)):
            rows = run_arm(tree.resolve(), data, args, overrides, Path(tmp) / name)
            kept = [r["images_per_s"] for r in rows if r["step"] > skip]
            if not kept:
                raise SystemExit(f"{name}: no logged step after step {skip} in {args.minutes} min "
                                 f"(last step {rows[-1]['step'] if rows else 0}); raise --minutes")
            rates[name] = statistics.median(kept)
            print(f"{name:9s} {tree.resolve()} {' '.join(overrides) or '(defaults)'}: "
                  f"{rates[name]:.1f} crops/s (median of {len(kept)} windows after step {skip}; "
                  f"{rows[-1]['step']} steps in {args.minutes} min)", flush=True)
    print(f"candidate / baseline: {rates['candidate'] / rates['baseline']:.2f}x")


if __name__ == "__main__":
    main()
