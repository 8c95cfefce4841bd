"""End-to-end frames/s of the video loop of `dope-hope infer`: onnxruntime against PyTorch.

    python bench/stream.py [--frames 60] [--repeats 2] [--threads 2] [--weights dope_hope/assets/demo_lite.pt]

Renders ``--frames`` scenes of `dope-hope demo` (configs/demo.yaml: one demo box among a few
distractors, 640x480, RealSense-like depth noise) with one fixed camera (no intrinsics
jitter), writes them as an mp4v video (MJPG .avi where mp4v is missing) and keeps each
frame's depth. Then, for each backend in turn, in this process, the loop of `dope-hope infer
clip.mp4` runs over the file: :func:`dope_hope.inference.stream_inference.predict_stream` on an
:class:`~dope_hope.io.streams.VideoFile` (decoded by OpenCV in the reader thread, every
frame processed), each frame's depth attached so that -LS runs, and per frame what the
command does: ``predict_many`` (network, decode + PnP, -LS), the JSON record, the overlay,
and the overlay written to an mp4v video (OpenMP's idle threads set to sleep, as `dope-hope
infer` does for streams: :func:`~dope_hope.inference.frame_loop.passive_openmp`). The lite
model runs through onnxruntime (exported
once at the video's working size, as `dope-hope export`) and through PyTorch; both with
``--threads`` threads; and, as the baseline of the ORT setting, through onnxruntime with its
intra-op threads spinning between runs (onnxruntime's default; dope-hope turns it off). The
three alternate ``--repeats`` times after a 3-frame warm-up of each, so that a change in the
machine's load hits all. Prints frames/s
end to end of every run (run_stream's count: from taking the first frame to the end of the
last), the detections, the load average, and the best run of each with their ratio.
"""
from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np
from video_with_depth import VideoWithDepth

from dope_hope.assets import DEMO_WEIGHTS
from dope_hope.demo.onnx_cache import ensure_onnx
from dope_hope.demo.scenes import DEMO_CONFIG, IMAGE_SIZE
from dope_hope.demo_object import DEMO_CLASS_NAME, demo_object_mesh, write_demo_object
from dope_hope.devices import cpu_line
from dope_hope.inference.frame_loop import passive_openmp
from dope_hope.io.camera import ImageCamera

TARGET_FPS = 15.0
SEED = 5000  # never used for training (demo_lite: seeds 1, 2) or the demo figures


def render(tmp: Path, n: int):
    """(video path, K, depths) of ``n`` demo scenes at 640x480, one camera."""
    import cv2

    from dope_hope.config import config_path, load_yaml, merge
    from dope_hope.synth import FrameGenerator

    mesh_path = write_demo_object(tmp / "mesh")
    cfg = merge(load_yaml(config_path(DEMO_CONFIG)),
                {"camera": {"focal_jitter": 0.0, "aspect_jitter": 0.0, "principal_jitter_px": 0.0}})
    depths, K = [], None
    writer, video = None, None
    with FrameGenerator(mesh_path, size=IMAGE_SIZE, config=cfg, class_name=DEMO_CLASS_NAME,
                        depth_noise=True, seed=SEED) as gen:
        for i in range(n):
            f = gen.render_frame(i)
            K = f.annotation.K
            if writer is None:
                for suffix, fourcc in ((".mp4", "mp4v"), (".avi", "MJPG")):
                    video = tmp / f"clip{suffix}"
                    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*fourcc), 30.0, IMAGE_SIZE)
                    if writer.isOpened():
                        break
            writer.write(cv2.cvtColor(f.rgb, cv2.COLOR_RGB2BGR))
            depths.append(f.depth.astype(np.float32))
    writer.release()
    return video, K, depths


def run_loop(predictor, video: Path, K: np.ndarray, depths: list, out: Path,
             max_frames: int | None = None):
    """The `dope-hope infer clip.mp4` loop over the file (its JSON lines and overlay video);
    (StreamStats, detections, detections refined by -LS)."""
    from dope_hope.inference.stream_inference import StreamSinks, predict_stream
    from dope_hope.io.video import OverlayVideo

    camera = ImageCamera(K=K, width=IMAGE_SIZE[0], height=IMAGE_SIZE[1], source=Path("bench"))
    source = VideoWithDepth(video, camera, depths)
    overlay = OverlayVideo(out, source.fps or 30.0)
    lines: list[str] = []
    result = predict_stream(source, [predictor], StreamSinks(on_record=lambda rec: lines.append(json.dumps(rec)),
                                                             video=overlay), max_frames=max_frames)
    overlay.close()
    return result.stats, len(lines), sum(r["ls_applied"] for r in result.records)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--weights", type=Path, default=DEMO_WEIGHTS)
    args = ap.parse_args()

    passive_openmp()  # as `dope-hope infer` does for a stream, before torch is imported
    from dope_hope.inference.backends import open_backend
    from dope_hope.inference.onnx_backend import OnnxBackend
    from dope_hope.inference.predictor import DopePredictor

    mesh = demo_object_mesh()
    # Network backends before any rendering: importing torch after the GL context crashes here.
    torch_backend = open_backend(args.weights, "torch", threads=args.threads)
    with tempfile.TemporaryDirectory(prefix="bench-stream-") as tmpdir:
        tmp = Path(tmpdir)
        torch_pred = DopePredictor(torch_backend, mesh=mesh)
        _, input_hw = torch_pred.working_size((IMAGE_SIZE[1], IMAGE_SIZE[0]))
        onnx_path, _ = ensure_onnx(args.weights, tmp, input_hw)
        onnx_pred = DopePredictor(open_backend(onnx_path, "onnx", threads=args.threads), mesh=mesh)
        spin_pred = DopePredictor(OnnxBackend(onnx_path, threads=args.threads, providers=["CPUExecutionProvider"],
                                              spinning=True), mesh=mesh)
        t0 = time.perf_counter()
        video, K, depths = render(tmp, args.frames)
        print(f"{cpu_line()}, {os.cpu_count()} CPUs, {args.threads} threads; {args.frames} frames "
              f"{IMAGE_SIZE[0]}x{IMAGE_SIZE[1]} rendered in {time.perf_counter() - t0:.1f} s -> {video.name}; "
              f"{args.weights.name} at network input {input_hw[1]}x{input_hw[0]}; "
              f"load average {os.getloadavg()[0]:.2f}", flush=True)
        backends = (("onnxruntime", onnx_pred), ("PyTorch", torch_pred), ("ORT spinning", spin_pred))
        for name, pred in backends:  # warm-up: first runs, caches
            run_loop(pred, video, K, depths, tmp / f"warm_{name}", max_frames=3)
        best: dict[str, float] = {}
        for r in range(args.repeats):
            for name, pred in backends:
                stats, n_det, n_ls = run_loop(pred, video, K, depths, tmp / f"overlay_{name}_{r}")
                best[name] = max(best.get(name, 0.0), stats.fps)
                print(f"{name:12s} run {r + 1}: {stats.summary()}; {n_det} detection(s), {n_ls} refined "
                      f"by -LS; load average {os.getloadavg()[0]:.2f}", flush=True)
    ort, pt, spin = best["onnxruntime"], best["PyTorch"], best["ORT spinning"]
    print(f"best of {args.repeats}: onnxruntime {ort:.1f} frames/s, PyTorch {pt:.1f} frames/s, onnxruntime "
          f"with spinning threads {spin:.1f} frames/s; onnxruntime / PyTorch {ort / pt:.2f}x, onnxruntime / "
          f"spinning {ort / spin:.2f}x end to end; onnxruntime "
          f"{'meets' if ort >= TARGET_FPS else 'misses'} the {TARGET_FPS:g} frames/s target")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
