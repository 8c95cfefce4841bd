"""Model cost: parameters, MACs and CPU forward time, side by side, with ratios.

1. DOPE-DR-400's decoder vs the VGG19 trunk it sits on (400x400 input, decoder on 6 stages).
2. lite vs DOPE-DR-50 at 200x200 and 400x400.

    python bench/model_cost.py [--threads 1] [--repeats 3]

MACs from torch.utils.flop_counter (conv/matmul FLOPs / 2). Times: median of ``--repeats``
forwards after one warm-up, batch 1, eval mode, ``torch.no_grad``.
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch
from torch.utils.flop_counter import FlopCounterMode

from dope_hope.config import load_config
from dope_hope.model import build_model


def params(module: torch.nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


def cost(fn, *args, repeats: int) -> tuple[float, float]:
    """(GMAC, median seconds) of ``fn(*args)``."""
    with torch.no_grad():
        with FlopCounterMode(display=False) as counter:
            fn(*args)
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            fn(*args)
            times.append(time.perf_counter() - t0)
    return counter.get_total_flops() / 2e9, statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    r = args.repeats

    print(f"torch {torch.__version__}, {args.threads} thread(s), median of {r}\n")
    print("== DOPE-DR-400 decoder vs VGG19 trunk (400x400 input, 6 stages decoded)")
    dr400 = build_model(load_config("dope_dr_400")).eval()
    x = torch.randn(1, 3, 400, 400)
    with torch.no_grad():
        feats = dr400.vgg(x)
        maps = [(torch.randn(1, 9, 50, 50), torch.randn(1, 16, 50, 50)) for _ in range(6)]
    trunk_mac, trunk_s = cost(dr400.vgg, x, repeats=r)
    dec_mac, dec_s = cost(dr400.decoder, maps, feats, repeats=r)
    all_mac, all_s = cost(dr400, x, repeats=r)
    rows = [("trunk (vgg.*)", params(dr400.vgg), trunk_mac, trunk_s),
            ("decoder (decoder.*)", params(dr400.decoder), dec_mac, dec_s),
            ("whole DOPE-DR-400", params(dr400), all_mac, all_s)]
    print(f"{'part':22s} {'params M':>9s} {'GMAC':>8s} {'ms':>9s}")
    for name, n, mac, s in rows:
        print(f"{name:22s} {n / 1e6:9.3f} {mac:8.2f} {s * 1e3:9.1f}")
    print(f"decoder / trunk: params {params(dr400.decoder) / params(dr400.vgg):.3f}, "
          f"MAC {dec_mac / trunk_mac:.3f}, time {dec_s / trunk_s:.3f}")
    del dr400

    print("\n== lite vs DOPE-DR-50")
    dr50 = build_model(load_config("dope_dr_50")).eval()
    lite = build_model(load_config("lite")).eval()
    print(f"params: lite {params(lite) / 1e6:.3f} M, DOPE-DR-50 {params(dr50) / 1e6:.3f} M, "
          f"ratio {params(lite) / params(dr50):.4f}")
    print(f"{'input':>8s} {'lite GMAC':>10s} {'lite ms':>8s} {'DR-50 GMAC':>11s} {'DR-50 ms':>9s} "
          f"{'MAC ratio':>10s} {'speed-up':>9s}")
    for size in (200, 400):
        x = torch.randn(1, 3, size, size)
        lm, ls = cost(lite, x, repeats=max(r, 10))
        dm, ds = cost(dr50, x, repeats=r)
        print(f"{size:>4d}x{size:<3d} {lm:10.3f} {ls * 1e3:8.1f} {dm:11.2f} {ds * 1e3:9.1f} "
              f"{lm / dm:10.4f} {ds / ls:8.1f}x")


if __name__ == "__main__":
    main()
