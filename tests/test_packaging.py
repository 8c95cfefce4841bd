"""A built wheel (not an editable checkout) carries what the commands need: the packaged
configs, the shipped demo model, `python -m dope_hope`."""
from __future__ import annotations

import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def unpacked_wheel(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    res = subprocess.run([sys.executable, "-m", "pip", "wheel", str(REPO), "--no-deps", "--no-build-isolation",
                          "-q", "-w", str(out)], capture_output=True, text=True, timeout=300)
    if res.returncode != 0:
        pytest.fail(f"pip wheel failed: {res.stderr[-2000:]}")
    (wheel,) = out.glob("dope_hope-*.whl")
    site = out / "site"
    with zipfile.ZipFile(wheel) as zf:
        zf.extractall(site)
    return site


def test_wheel_holds_configs_model_and_entry_points(unpacked_wheel):
    pkg = unpacked_wheel / "dope_hope"
    assert {p.stem for p in (pkg / "configs").glob("*.yaml")} >= {
        "lite", "dope_dr_50", "dope_dr_400", "synth", "demo", "procedural", "infer"}
    assert (pkg / "assets" / "demo_lite.pt").is_file() and (pkg / "__main__.py").is_file()
    assert (pkg / "assets" / "pretrained_lite.pt").is_file()  # the default start of a lite run


def test_wheel_finds_its_configs_outside_the_repository(unpacked_wheel, tmp_path):
    code = ("import dope_hope, sys; from dope_hope.config import CONFIG_DIR, load_config; "
            "assert str(CONFIG_DIR).startswith(sys.argv[1]), CONFIG_DIR; "
            "assert load_config('lite')['model']['arch'] == 'lite'; "
            "from dope_hope.inference.options import InferenceOptions; InferenceOptions.from_mapping(); "
            "print(dope_hope.build_model('lite').stride)")
    env = {**os.environ, "PYTHONPATH": str(unpacked_wheel)}
    res = subprocess.run([sys.executable, "-c", code, str(unpacked_wheel)], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    assert res.stdout.strip() == "4"
    res = subprocess.run([sys.executable, "-m", "dope_hope", "objects"], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0 and "Ketchup" in res.stdout
