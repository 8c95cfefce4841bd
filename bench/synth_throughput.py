"""Synthetic data generator throughput: frames/s at 640x480 and 400x400 with 1 and 2 workers.

Candidate: --workers 2 (two spawned render processes, one EGL context each); baseline:
--workers 1 (in-process). Prints, per size, end-to-end frames/s (process start, mesh load and
all frames, what a user sees) and steady-state frames/s (after every worker has written its
first frame), plus the ratio 2 workers / 1 worker.

    python bench/synth_throughput.py                    # 24 frames per setting
    python bench/synth_throughput.py --frames 40 --mesh ../shared/data/hope_ketchup/textured.obj

With --randomization it measures instead, with 1 worker, the default config (clutter
backgrounds, hard negatives, sensor artefacts) against the same config with those three off
(dope_hope.synth.settings.PLAIN_OVERRIDES: the generator's earlier frames), alternating, and
prints the ratio of the steady-state ms per frame.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from dope_hope.synth.generate import SynthJob  # noqa: E402
from dope_hope.synth.settings import PLAIN_OVERRIDES as PLAIN  # noqa: E402
from dope_hope.synth.to_disk import generate_dataset  # noqa: E402


def measure(mesh: Path, size: str, workers: int, frames: int, seed: int, config: dict | None = None,
            backgrounds: Path | None = None) -> tuple[float, float]:
    """(end-to-end frames/s, steady-state frames/s) of one fresh run."""
    stamps: list[float] = []
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        job = SynthJob(mesh, seed=seed, size=size, config=config, backgrounds=backgrounds)
        generate_dataset(Path(tmp) / "out", job, frames, workers=workers, progress=False,
                         on_frame=lambda i: stamps.append(time.perf_counter()))
        end = time.perf_counter()
    warm = workers  # frames completed before the steady-state window starts
    steady = (len(stamps) - warm) / (stamps[-1] - stamps[warm - 1]) if len(stamps) > warm + 1 else float("nan")
    return frames / (end - start), steady


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mesh", type=Path, default=REPO.parent / "shared" / "data" / "hope_ketchup" / "textured.obj")
    parser.add_argument("--frames", type=int, default=24)
    parser.add_argument("--sizes", nargs="+", default=["640x480", "400x400"])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--randomization", action="store_true",
                        help="default config against clutter / hard negatives / sensor artefacts off")
    parser.add_argument("--backgrounds", type=Path, help="background photos (--randomization)")
    parser.add_argument("--repeats", type=int, default=2, help="alternating runs each (--randomization)")
    args = parser.parse_args()
    if not args.mesh.is_file():
        sys.exit(f"mesh not found: {args.mesh} (the reference data lives in ../shared/data)")
    if args.randomization:
        compare_randomization(args)
        return
    print(f"mesh {args.mesh.name}, {args.frames} frames per setting, {os.cpu_count()} CPUs, "
          f"load average before: {os.getloadavg()[0]:.2f}")
    print(f"{'size':>8} {'workers':>7} {'end-to-end f/s':>15} {'steady f/s':>11}")
    for size in args.sizes:
        res = {}
        for workers in (1, 2):
            res[workers] = measure(args.mesh, size, workers, args.frames, args.seed)
            print(f"{size:>8} {workers:>7} {res[workers][0]:>15.2f} {res[workers][1]:>11.2f}", flush=True)
        print(f"{size:>8} ratio 2 workers / 1 worker: end-to-end {res[2][0] / res[1][0]:.2f}x, "
              f"steady {res[2][1] / res[1][1]:.2f}x")
    print(f"load average after: {os.getloadavg()[0]:.2f}")


def compare_randomization(args: argparse.Namespace) -> None:
    """Default config vs PLAIN_OVERRIDES, 1 worker, alternating runs; best steady ms per frame."""
    print(f"mesh {args.mesh.name}, {args.frames} frames per run, {args.repeats} runs each, backgrounds "
          f"{args.backgrounds}, {os.cpu_count()} CPUs, load average before: {os.getloadavg()[0]:.2f}")
    for size in args.sizes:
        best = {"default": float("inf"), "plain": float("inf")}
        for _ in range(args.repeats):
            for name, cfg in (("plain", PLAIN), ("default", None)):
                steady = measure(args.mesh, size, 1, args.frames, args.seed, cfg, args.backgrounds)[1]
                best[name] = min(best[name], 1000.0 / steady)
        print(f"{size:>8}: ms/frame (steady, best of {args.repeats}) plain {best['plain']:.1f}, default "
              f"{best['default']:.1f}; ratio default / plain {best['default'] / best['plain']:.2f}x", flush=True)
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
