"""CPU inference: PyTorch eager vs onnxruntime fp32 vs onnxruntime INT8, DOPE-DR-50.

    python bench/cpu_inference.py [--sizes 480x640 400x400] [--runs 10] [--warmup 2]
                                  [--threads N] [--calibration-images 8] [--eval-images 4]

Per input size (H x W) it exports the DR-50 checkpoint to a static fp32 ONNX file and
quantizes it (static INT8, QDQ, per-channel; calibrated on synthetic images prepared like
the predictor does), then times each backend **in its own subprocess** (batch 1, median of
``--runs`` forwards after ``--warmup``): PyTorch eager (``load_model`` + ``model(x)`` under
``inference_mode``), onnxruntime fp32 and INT8 (:class:`dope_hope.inference.onnx_backend.OnnxBackend`,
graph optimization "all"). Peak memory is the subprocess's VmHWM (/proc/self/status; native
allocations included; tracemalloc would miss them; not ``ru_maxrss``, which Linux carries
over fork + exec from the parent), next to its RSS after imports.
The three run one after another with the same thread count, so the ratios are the figures.

**Weights.** No trained DR-50 exists here, and latency does not depend on the weight
values, so timing uses a seeded random DR-50. Its raw outputs are ~50 in size (Kaiming init
without normalization, compounded over six stages), so one data-dependent rescaling pass
(LSUV-style: each conv's weights and bias divided by its output std on one synthetic image;
exact for ReLU networks) brings the maps to the ~0-1 range of a trained model. These maps
have structure (smooth blobs with sub-pixel peaks) but no meaning: the DR-50 INT8 figures
(map difference; deviation of every belief peak, matched one-to-one within one cell) say how
much INT8 moves peaks of maps like these; decoded-instance keypoints are meaningless there.
A second DR-50 figure adds the measured INT8-minus-fp32 map differences to ideal target maps
of the images' true keypoints (the sharp isolated peaks a trained DR-50 aims for, sigma of
``dope_dr_50.yaml``) and decodes them: what an error of that absolute size does to such
peaks (a trained network's INT8 error may be smaller or larger than a random one's).
The **keypoint** deviation of decoded instances is measured on a lite network briefly fitted
end to end on a synthetic box scene (bench/fit_one.py, the same model the tests
use: a trained network whose maps decode one clean instance) and on held-out jittered
copies of the scene. Evaluation images are never calibration images.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent


# ----------------------------------------------------------------------------- worker
def _rss_mb(key: str = "VmRSS") -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def worker(args: argparse.Namespace) -> None:
    """Time one backend; print one JSON line."""
    h, w = (int(v) for v in args.size.split("x"))
    x = np.random.default_rng(0).standard_normal((1, 3, h, w)).astype(np.float32)
    if args.worker == "torch":
        import torch

        torch.set_num_threads(args.threads)
        from dope_hope.model.checkpoint import load_model

        base = _rss_mb()
        model, _ = load_model(args.model)
        xt = torch.from_numpy(x)

        def forward():
            with torch.inference_mode():
                return model(xt)[-1]
    else:
        from dope_hope.inference.onnx_backend import OnnxBackend

        base = _rss_mb()
        backend = OnnxBackend(args.model, threads=args.threads, providers=["CPUExecutionProvider"])

        def forward():
            return backend.run(x)
    for _ in range(args.warmup):
        forward()
    times = []
    for _ in range(args.runs):
        t0 = time.perf_counter()
        forward()
        times.append(time.perf_counter() - t0)
    # VmHWM, not ru_maxrss: Linux keeps ru_maxrss across fork + exec, so a child of a big parent
    # would report the parent's size; VmHWM belongs to the new address space.
    peak_mb = _rss_mb("VmHWM")
    print(json.dumps({"median_s": statistics.median(times), "min_s": min(times), "times": times,
                      "rss_after_imports_mb": base, "peak_rss_mb": peak_mb}))


def run_worker(kind: str, model: Path, size: str, runs: int, warmup: int, threads: int) -> dict:
    cmd = [sys.executable, __file__, "--worker", kind, "--model", str(model), "--size", size,
           "--runs", str(runs), "--warmup", str(warmup), "--threads", str(threads)]
    env = dict(os.environ, OMP_NUM_THREADS=str(threads))
    out = subprocess.run(cmd, check=True, capture_output=True, text=True, env=env)
    return json.loads(out.stdout.strip().splitlines()[-1])


# ----------------------------------------------------------------------------- data
def scene_image(hw: tuple[int, int], seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(rgb (H, W, 3) uint8, keypoints (9, 2)): the Ketchup box drawn at a jittered pose."""
    import cv2
    from scipy.spatial.transform import Rotation

    from dope_hope.catalog import get_object
    from dope_hope.geometry import CUBOID_EDGES, cuboid_keypoints, project_points

    rng = np.random.default_rng(seed)
    H, W = hw
    f = 0.9 * W
    K = np.array([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1.0]])
    R = Rotation.from_euler("xyz", [25 + rng.uniform(-15, 15), -35 + rng.uniform(-15, 15),
                                    rng.uniform(-20, 20)], degrees=True).as_matrix()
    t = np.array([rng.uniform(-0.05, 0.05), rng.uniform(-0.04, 0.04), rng.uniform(0.35, 0.6)])
    kp = project_points(cuboid_keypoints(get_object("Ketchup").size_array), K, R, t)
    tiles = rng.integers(30, 220, (H // 16 + 1, W // 16 + 1, 3)).astype(np.uint8)
    rgb = cv2.resize(tiles, (W // 16 * 16 + 16, H // 16 * 16 + 16), interpolation=cv2.INTER_NEAREST)[:H, :W].copy()
    cv2.fillConvexPoly(rgb, cv2.convexHull(np.round(kp[:8]).astype(np.int32)), (200, 40, 40))
    for a, b in CUBOID_EDGES:
        cv2.line(rgb, tuple(int(v) for v in np.round(kp[a])), tuple(int(v) for v in np.round(kp[b])),
                 (250, 250, 250), max(1, W // 200))
    return rgb, kp


def lsuv_rescale(model, rgb: np.ndarray) -> None:
    """Divide each conv's weights (and bias) by its output std on ``rgb``, in one forward pass.

    The hooks run in forward order, so every layer sees its already rescaled inputs; exact for
    ReLU networks (eval-mode BatchNorm is affine). Random init -> unit-scale activations.
    """
    import torch

    from dope_hope.model.network import normalize_image

    def rescale(module, inputs, output):
        s = output.std().clamp_min(1e-8)
        module.weight.div_(s)
        if module.bias is not None:
            module.bias.div_(s)
        return output / s

    model.eval()
    hooks = [m.register_forward_hook(rescale) for m in model.modules() if isinstance(m, torch.nn.Conv2d)]
    with torch.no_grad():
        model(normalize_image(rgb)[None])
    for h in hooks:
        h.remove()


def random_checkpoint(path: Path, config: dict, seed: int = 0) -> Path:
    """Seeded random network of ``config``, LSUV-rescaled (module docstring), as a checkpoint."""
    import torch

    from dope_hope.model.checkpoint import save_checkpoint
    from dope_hope.model.network import build_model

    torch.manual_seed(seed)
    model = build_model(config)
    lsuv_rescale(model, scene_image(tuple(config["input"]["size"]), seed=10_000)[0])
    save_checkpoint(path, model, config, {"class_name": "Ketchup"},
                    source="bench/cpu_inference.py: random weights, LSUV-rescaled (untrained)")
    return path


def write_images(folder: Path, hw: tuple[int, int], seeds: range) -> list[tuple[Path, np.ndarray]]:
    """Scene images written as PNG: [(path, keypoints (9, 2) image px)]."""
    from dope_hope.io.images import write_rgb

    out = []
    for s in seeds:
        p = folder / f"{s:06d}.png"
        rgb, kp = scene_image(hw, s)
        write_rgb(p, rgb)
        out.append((p, kp))
    return out


def int8_deviation(fp32_path: Path, int8_path: Path, images: list[tuple[Path, np.ndarray]],
                   transfer_sigma: float | None = None):
    """INT8 vs fp32 on held-out images prepared by the predictor: (compare_maps, transfer).

    ``transfer`` (with ``transfer_sigma``): the measured INT8-minus-fp32 map differences added
    to ideal target maps of the image's true keypoints (``targets.make_targets``, sigma in map
    px), decoded and compared with the clean targets' decoding: what INT8's error would do to
    the sharp, isolated peaks of a trained model (None without ``transfer_sigma``).
    """
    from dope_hope.export.compare import compare_maps
    from dope_hope.inference.onnx_backend import OnnxBackend
    from dope_hope.inference.predictor import DopePredictor
    from dope_hope.io.images import read_rgb
    from dope_hope.maps.targets import make_targets

    fp32, int8 = OnnxBackend(fp32_path), OnnxBackend(int8_path)
    prep = DopePredictor(fp32)
    ref, test, clean, noisy = [], [], [], []
    for p, kp in images:
        net_in = prep.prepare(read_rgb(p))
        r = tuple(m[0] for m in fp32.run(net_in.batch))
        t = tuple(m[0] for m in int8.run(net_in.batch))
        ref.append(r)
        test.append(t)
        if transfer_sigma is not None:
            b, a = make_targets(net_in.to_network_px(kp)[None], net_in.batch.shape[2:], fp32.stride,
                                sigma=transfer_sigma, radius=1.0)
            clean.append((b, a))
            noisy.append((b + (t[0] - r[0]), a + (t[1] - r[1])))
    transfer = compare_maps(clean, noisy, fp32.stride) if clean else None
    return compare_maps(ref, test, fp32.stride), transfer


def lite_keypoints(tmp: Path, n_eval: int) -> tuple:
    """INT8 vs fp32 of the fitted lite model and, as a control, the same lite untrained.

    Both calibrate and evaluate on the same jittered copies of the fitted scene (held out from
    calibration). Returns (input (H, W), fitted deviation, untrained deviation).
    """
    from fit_one import IMAGE_HW, fit_lite_checkpoint  # bench/fit_one.py, beside this script
    from fit_one import box_scene as scene

    from dope_hope.config import load_settings
    from dope_hope.export.pipeline import Int8Calibration, export_checkpoint
    from dope_hope.io.images import write_rgb
    from dope_hope.training.settings import TrainConfig

    rgb, _ = scene()
    rng = np.random.default_rng(123)
    calib, evald = tmp / "lite_calib", tmp / "lite_eval"
    for i in range(8 + n_eval):
        img = np.clip(rgb.astype(int) + rng.integers(-25, 25, rgb.shape), 0, 255).astype(np.uint8)
        write_rgb((calib if i < 8 else evald) / f"{i:06d}.png", img)
    cfg = load_settings(TrainConfig, "lite").to_dict()  # every section, over the defaults
    cfg["input"]["size"] = list(IMAGE_HW)
    out = []
    for name, ckpt in (("fitted", fit_lite_checkpoint(tmp / "lite_fitted.pt")),
                       ("untrained", random_checkpoint(tmp / "lite_random.pt", cfg))):
        fp32 = export_checkpoint(ckpt, tmp / f"lite_{name}.onnx")
        export_checkpoint(ckpt, tmp / f"lite_{name}_int8.onnx", int8=Int8Calibration(calib))
        dev, _ = int8_deviation(fp32.path, tmp / f"lite_{name}_int8.onnx",
                                [(p, None) for p in sorted(evald.iterdir())])
        out.append(dev)
    return (IMAGE_HW, *out)


def demo_keypoints(tmp: Path, n_calib: int, n_eval: int):
    """INT8 vs fp32 of the shipped demo model (trained lite, DemoBox) on synthetic demo frames.

    Frames come from ``dope-hope synth`` with the demo object (as in bench/RESULTS.md, demo
    section): calibration and evaluation folders use different seeds. None without the model.
    """
    demo = REPO / "dope_hope" / "assets" / "demo_lite.pt"
    if not demo.is_file():
        return None
    from dope_hope.demo_object import write_demo_object
    from dope_hope.export.pipeline import Int8Calibration, export_checkpoint

    mesh = write_demo_object(tmp / "demo_mesh")
    folders = {}
    for name, seed, count in (("calib", 3, n_calib), ("eval", 4, n_eval)):
        folders[name] = tmp / f"demo_{name}"
        subprocess.run([sys.executable, "-m", "dope_hope.cli", "synth", "--mesh", str(mesh),
                        "--class-name", "DemoBox", "--out", str(folders[name]), "--count", str(count),
                        "--seed", str(seed), "--size", "320x240", "--no-progress", "--set",
                        "target.count=[1,2]", "target.distance_m=[0.4,1.0]"],
                       check=True, capture_output=True)
    fp32 = export_checkpoint(demo, tmp / "demo_fp32.onnx")
    export_checkpoint(demo, tmp / "demo_int8.onnx", int8=Int8Calibration(folders["calib"]))
    frames = sorted(p for p in folders["eval"].glob("*.png") if p.name.count(".") == 1)
    dev, _ = int8_deviation(fp32.path, tmp / "demo_int8.onnx", [(p, None) for p in frames])
    return fp32.info.fixed_input_hw, dev


# ----------------------------------------------------------------------------- main
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", nargs="+", default=["480x640", "400x400"], help="H x W input sizes")
    ap.add_argument("--runs", type=int, default=10)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--threads", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--calibration-images", type=int, default=8)
    ap.add_argument("--eval-images", type=int, default=4)
    ap.add_argument("--no-lite", action="store_true", help="skip the lite / demo-model keypoint checks")
    ap.add_argument("--worker", choices=("torch", "onnx"), help=argparse.SUPPRESS)
    ap.add_argument("--model", help=argparse.SUPPRESS)
    ap.add_argument("--size", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        worker(args)
        return

    import onnxruntime
    import torch

    from dope_hope.config import load_settings
    from dope_hope.export.int8 import cpu_int8_support, quantize_int8
    from dope_hope.export.pipeline import export_checkpoint
    from dope_hope.export.to_onnx import ExportSettings
    from dope_hope.training.settings import TrainConfig

    print(f"torch {torch.__version__}, onnxruntime {onnxruntime.__version__}, {args.threads} threads, "
          f"{os.cpu_count()} CPUs ({cpu_int8_support()[1]}); load average at start "
          f"{os.getloadavg()[0]:.2f}", flush=True)
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-cpu-inference-") as tmpdir:
        tmp = Path(tmpdir)
        t0 = time.perf_counter()
        cfg = load_settings(TrainConfig, "dope_dr_50").to_dict()  # every section, over the defaults
        cfg["input"]["size"] = [200, 200]  # the LSUV image; the exports set their own size
        ckpt = random_checkpoint(tmp / "dr50.pt", cfg)
        sigma = float(cfg["targets"]["sigma"])  # training target blob, map px
        print(f"DR-50 checkpoint (random, LSUV-rescaled): {time.perf_counter() - t0:.1f} s", flush=True)
        calib = write_images(tmp / "calib", (480, 640), range(args.calibration_images))
        evals = write_images(tmp / "eval", (480, 640), range(1000, 1000 + args.eval_images))
        for size in args.sizes:
            h, w = (int(v) for v in size.split("x"))
            t0 = time.perf_counter()
            fp32 = export_checkpoint(ckpt, tmp / f"dr50_{size}.onnx", ExportSettings(input_hw=(h, w)))
            t_export = time.perf_counter() - t0
            t0 = time.perf_counter()
            int8_path = tmp / f"dr50_{size}_int8.onnx"
            quantize_int8(fp32.path, int8_path, calib[0][0].parent, max_images=len(calib), eval_images=1)
            t_quant = time.perf_counter() - t0
            dev, transfer = int8_deviation(fp32.path, int8_path, evals, transfer_sigma=sigma)
            print(f"[{size}] export {t_export:.1f} s (verify max |d| {fp32.verify_max_abs:.1e}), INT8 "
                  f"quantization {t_quant:.1f} s; INT8 vs fp32: {dev.summary()}; transfer to ideal "
                  f"maps: {transfer.summary()}", flush=True)
            res = {}
            for name, kind, model in (("pytorch", "torch", ckpt), ("ort_fp32", "onnx", fp32.path),
                                      ("ort_int8", "onnx", int8_path)):
                res[name] = run_worker(kind, model, size, args.runs, args.warmup, args.threads)
                r = res[name]
                print(f"[{size}] {name:9s} median {1000 * r['median_s']:8.1f} ms (min {1000 * r['min_s']:.1f}), "
                      f"peak RSS {r['peak_rss_mb']:.0f} MB (after imports {r['rss_after_imports_mb']:.0f} MB); "
                      f"load {os.getloadavg()[0]:.2f}", flush=True)
            rows.append((size, res, dev, transfer, fp32.size_bytes, int8_path.stat().st_size))
        lite = None if args.no_lite else lite_keypoints(tmp, args.eval_images)
        demo = None if args.no_lite else demo_keypoints(tmp, 8, 8)

    print("\n| input HxW | backend | median ms | x PyTorch | peak RSS MB | model file MB |")
    print("|---|---|---|---|---|---|")
    for size, res, _, _, fp32_bytes, int8_bytes in rows:
        base = res["pytorch"]["median_s"]
        for name, label, mb in (("pytorch", "PyTorch eager (fp32)", None), ("ort_fp32", "onnxruntime fp32", fp32_bytes),
                                ("ort_int8", "onnxruntime INT8 (QDQ)", int8_bytes)):
            r = res[name]
            print(f"| {size} | {label} | {1000 * r['median_s']:.0f} | {base / r['median_s']:.2f}x | "
                  f"{r['peak_rss_mb']:.0f} | {'' if mb is None else f'{mb / 1e6:.0f}'} |")
    print("\nINT8 vs fp32 (held-out images):")
    for size, _, dev, transfer, _, _ in rows:
        print(f"- DR-50 {size}, untrained (maps of random blobs): {dev.summary()}")
        print(f"- DR-50 {size}, its INT8 error added to ideal sigma-{sigma:g} target maps of the true "
              f"keypoints: {transfer.summary()}")
    if lite is not None:
        print(f"- lite fitted to the scene, {lite[0][0]}x{lite[0][1]} (decoded instances): {lite[1].summary()}")
        print(f"- control, the same lite untrained (LSUV-rescaled), same images: {lite[2].summary()}")
    if demo is not None:
        print(f"- shipped demo model (trained lite, DemoBox), {demo[0][0]}x{demo[0][1]}, 8 held-out "
              f"synthetic frames: {demo[1].summary()}")
    print(f"load average at end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
