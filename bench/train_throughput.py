"""Training throughput: lite vs DOPE-DR-50, images/s of full training steps, side by side.

Each model trains with the project's own step (``dope_hope.training.optimizer_step``: forward,
per-stage MSE, backward, Adam step) on batches of ``--batch`` images of its config's training
item size (lite: its 128x128 object-centred crops, ``augment.crop``; DOPE-DR-50 400x400),
with real belief/affinity targets. A warm-up
step is not timed. Besides wall-clock images/s it prints the process CPU time per image,
which on a shared machine (other jobs competing for the cores) tracks the uncontended cost
better than wall time does, above all with one thread. Each model runs as the trainer runs it
(its config's ``train.amp``: bf16 autocast where the device computes bf16 natively, and
``train.channels_last``), on the CPU and, when available, on CUDA. ``--precision`` also times
lite on the CPU in plain float32 NCHW (the baseline) and prints the recipe's ratio to it.

    python bench/train_throughput.py [--batch 2] [--steps-lite 10] [--steps-dr50 3] [--threads 2] [--precision]
    python bench/train_throughput.py --device cuda --batch 32     # the GPU alone
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from dope_hope.config import load_config
from dope_hope.devices import native_bf16
from dope_hope.maps.targets import make_targets
from dope_hope.model import build_model
from dope_hope.training.augment import crop_size
from dope_hope.training.loss import optimizer_step
from dope_hope.training.settings import TrainConfig


def item_hw(recipe: TrainConfig) -> tuple[int, int]:
    """(H, W) of the recipe's training items: the input size, or its augmentation crop."""
    return crop_size(recipe.augment, recipe.input.size)


def batch_for(recipe: TrainConfig, stride: int, batch: int, device: torch.device):
    H, W = item_hw(recipe)
    rng = np.random.default_rng(0)
    tc = recipe.targets
    beliefs, affinities = [], []
    for _ in range(batch):
        kp = np.stack([rng.uniform(0.2 * W, 0.8 * W, 9), rng.uniform(0.2 * H, 0.8 * H, 9)], 1)[None]
        b, a = make_targets(kp, (H, W), stride, float(tc.sigma), float(tc.radius))
        beliefs.append(b)
        affinities.append(a)
    images = torch.randn(batch, 3, H, W)
    return (images.to(device), torch.from_numpy(np.stack(beliefs)).to(device),
            torch.from_numpy(np.stack(affinities)).to(device))


def measure(name: str, batch: int, steps: int, warmup: int, device: torch.device,
            recipe: bool = True) -> tuple[float, float]:
    """(images per second, process CPU seconds per image) of training steps for the config
    ``name``: as the trainer runs it (``recipe``: the config's amp where native, its
    channels_last), or in plain float32 NCHW."""
    config = TrainConfig.from_mapping(load_config(name))
    ts = config.train
    amp = recipe and bool(ts.amp) and native_bf16(device.type)
    channels_last = recipe and bool(ts.channels_last)
    torch.manual_seed(0)
    model = build_model(config.to_dict()).to(device)
    cuda = device.type == "cuda"
    images, belief, affinity = batch_for(config, model.stride, batch, device)
    if channels_last:
        model = model.to(memory_format=torch.channels_last)
        images = images.contiguous(memory_format=torch.channels_last)
    opt = torch.optim.Adam(model.parameters(), lr=1e-5)
    for _ in range(warmup):
        optimizer_step(model, opt, images, belief, affinity, amp=amp)
    if cuda:
        torch.cuda.synchronize()
    t0, c0 = time.perf_counter(), time.process_time()
    for _ in range(steps):
        optimizer_step(model, opt, images, belief, affinity, amp=amp)
    if cuda:
        torch.cuda.synchronize()
    dt, cpu = time.perf_counter() - t0, time.process_time() - c0
    ips = steps * batch / dt
    H, W = item_hw(config)
    label = name + (" bf16" if amp else " fp32") + (" NHWC" if channels_last else "")
    print(f"  {label:<20} {W}x{H}  batch {batch}: {dt / steps * 1000:9.1f} ms/step  {ips:8.2f} images/s  "
          f"(process CPU {cpu / (steps * batch) * 1000:.0f} ms/image)")
    return ips, cpu / (steps * batch)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--batch", type=int, default=2)
    ap.add_argument("--steps-lite", type=int, default=10)
    ap.add_argument("--steps-dr50", type=int, default=3, help="0: lite only")
    ap.add_argument("--warmup", type=int, default=1)
    ap.add_argument("--threads", type=int, default=2, help="torch threads on CPU")
    ap.add_argument("--device", choices=("all", "cpu", "cuda"), default="all",
                    help="where to time: the CPU, CUDA, or both (all: CUDA when available)")
    ap.add_argument("--precision", action="store_true",
                    help="also time lite on the CPU in plain float32 NCHW, and the recipe's ratio to it")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    if args.device == "cuda" and not torch.cuda.is_available():
        raise SystemExit("--device cuda: no CUDA device available")
    devices = [torch.device(name) for name in ("cpu", "cuda") if args.device in ("all", name)
               and (name == "cpu" or torch.cuda.is_available())]
    for device in devices:
        label = f"CPU, {args.threads} thread(s)" if device.type == "cpu" else torch.cuda.get_device_name(0)
        print(f"{label}:")
        scale = 1 if device.type == "cpu" else 10
        lite, lite_cpu = measure("lite", args.batch, args.steps_lite * scale, args.warmup, device)
        if args.precision and device.type == "cpu":
            plain, plain_cpu = measure("lite", args.batch, args.steps_lite, args.warmup, device, recipe=False)
            print(f"  ratio lite recipe / plain float32 NCHW: {lite / plain:.2f}x images/s (wall), "
                  f"{plain_cpu / lite_cpu:.2f}x (process CPU time per image)")
        if args.steps_dr50 <= 0:  # lite only (DR-50 on a CPU costs minutes)
            continue
        dr50, dr50_cpu = measure("dope_dr_50", args.batch, args.steps_dr50 * scale, args.warmup, device)
        print(f"  ratio lite / DOPE-DR-50: {lite / dr50:.1f}x images/s (wall), "
              f"{dr50_cpu / lite_cpu:.1f}x (process CPU time per image)")


if __name__ == "__main__":
    main()
