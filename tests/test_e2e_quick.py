"""bench/e2e_accuracy.py --quick: every stage of the end-to-end benchmark runs (real CLI
subprocesses on the HOPE Ketchup mesh, tiny sizes), writes its table, and a rerun resumes
(skips every finished stage). The numbers of a --quick run are meaningless; this only keeps
the script from rotting. ~30-40 s on 2 shared cores."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
STAGES = ("synth-train", "train", "synth-test", "infer-ls", "infer", "infer-icp", "eval-meanssd", "eval-addh")


@pytest.mark.slow
def test_quick_run_writes_the_table_and_resumes(shared_data, ketchup_obj, tmp_path):
    out = tmp_path / "e2e"
    cmd = [sys.executable, str(REPO / "bench" / "e2e_accuracy.py"), "--quick", "--out", str(out),
           "--mesh", str(ketchup_obj), "--backgrounds", str(shared_data / "backgrounds")]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    for stage in STAGES:  # each stage printed the exact command a user would type
        assert f"[{stage}] $ dope-hope " in proc.stdout
    assert "--depth auto" in proc.stdout and "--depth-noise" in proc.stdout and "--icp" in proc.stdout
    train_line = next(line for line in proc.stdout.splitlines() if line.startswith("[train] $"))
    assert "targets.symmetry=auto" in train_line and "input.size=[64,64]" in train_line  # the default, one --set
    assert train_line.count("--set") == 1
    assert "symmetry-aware labels: bottle category, 2 corner-permuting" in (out / "logs" / "train.log").read_text()
    table = [line for line in proc.stdout.splitlines() if line.startswith("| lite |")]
    assert [line.split("|")[2].strip() for line in table] == ["-LS", "none", "-LS+ICP"]
    assert all(len(line.split("|")) == 13 for line in table)
    results = json.loads((out / "results.json").read_text())
    assert set(results["results"]) == {"lite -LS", "lite none", "lite -LS+ICP"}
    for row in results["results"].values():
        assert {"recall_2cm_meanssd", "recall_10cm_addh", "median_addh_cm", "ar_mssd", "ar_mspd"} <= set(row)
        assert 0.0 <= row["recall_2cm_meanssd"] <= 1.0 and 0.0 <= row["ar_mssd"] <= 1.0
    assert (out / "results.md").read_text().count("| lite |") == 3
    assert len(list((out / "test").glob("*.depth.png"))) == 3

    again = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert again.returncode == 0, again.stderr[-2000:]
    assert all(f"[{s}] done earlier, skipped" in again.stdout for s in STAGES)

    other = subprocess.run(cmd + ["--test-count", "4"], capture_output=True, text=True, timeout=60)
    assert other.returncode != 0 and "other settings (test_count)" in (other.stdout + other.stderr)
