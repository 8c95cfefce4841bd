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
STAGES = ("synth-train", "train", "synth-test", "infer-ls", "infer", "infer-icp", "infer-turns", "infer-scales",
          "infer-default", "eval-meanssd", "eval-addh", "eval-bop19")


@pytest.mark.slow
def test_quick_run_writes_the_table_and_resumes(shared_data, ketchup_obj, tmp_path):
    out = tmp_path / "e2e"
    cmd = [sys.executable, str(REPO / "bench" / "e2e_accuracy.py"), "--quick", "--out", str(out),
           "--mesh", str(ketchup_obj), "--backgrounds", str(shared_data / "backgrounds")]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=420)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    for stage in STAGES:  # each stage printed the exact command a user would type
        assert f"[{stage}] $ dope-hope " in proc.stdout
    assert "--depth auto" in proc.stdout and "--depth-noise" in proc.stdout and "--icp" in proc.stdout
    train_line = next(line for line in proc.stdout.splitlines() if line.startswith("[train] $"))
    assert "targets.symmetry=auto" in train_line and "input.size=[64,64]" in train_line  # the default, one --set
    assert train_line.count("--set") == 1
    assert "symmetry-aware labels: bottle category, 2 corner-permuting" in (out / "logs" / "train.log").read_text()
    table = [line for line in proc.stdout.splitlines() if line.startswith("| lite |")]
    assert [line.split("|")[2].strip() for line in table] == ["-LS", "none", "-LS+ICP", "turns+-LS", "scales+-LS",
                                                              "default"]
    assert all(len(line.split("|")) == 15 for line in table)  # BOP19's targets' recall in the last two
    results = json.loads((out / "results.json").read_text())
    assert set(results["results"]) == {"lite -LS", "lite none", "lite -LS+ICP", "lite turns+-LS", "lite scales+-LS",
                                       "lite default"}
    for row in results["results"].values():
        assert {"recall_2cm_meanssd", "recall_10cm_addh", "median_addh_cm", "ar_mssd", "ar_mspd",
                "recall_2cm_meanssd_bop_targets"} <= set(row)
        assert 0.0 <= row["recall_2cm_meanssd"] <= 1.0 and 0.0 <= row["ar_mssd"] <= 1.0
    assert (out / "results.md").read_text().count("| lite |") == 6
    turns_line = next(line for line in proc.stdout.splitlines() if line.startswith("[infer-turns] $"))
    assert "--set appearance.trained_turns=true" in turns_line and "--depth auto" in turns_line
    scales_line = next(line for line in proc.stdout.splitlines() if line.startswith("[infer-scales] $"))
    assert "--set 'multiscale.scales=[1,0.75,1.33]'" in scales_line and "--depth auto" in scales_line
    assert "--fast" in scales_line and "--fast" in turns_line  # each method: the packaged defaults, one change
    default_line = next(line for line in proc.stdout.splitlines() if line.startswith("[infer-default] $"))
    assert "--fast" not in default_line and "--set" not in default_line and "--depth auto" in default_line
    bop_line = next(line for line in proc.stdout.splitlines() if line.startswith("[eval-bop19] $"))
    assert "--min-visible bop19" in bop_line
    assert len(list((out / "test").glob("*.depth.png"))) == 3
    # what is measured: the default recipe's training frames, the CPU, the budget spent, the losses
    synth_train = next(line for line in proc.stdout.splitlines() if line.startswith("[synth-train] $"))
    synth_test = next(line for line in proc.stdout.splitlines() if line.startswith("[synth-test] $"))
    assert "clutter_prob" not in synth_train and "--backgrounds" not in synth_train
    assert "background.clutter_prob=0.0" in synth_test and "--backgrounds" in synth_test
    assert proc.stdout.splitlines()[0].startswith("CPU ") and "avx512_bf16" in proc.stdout.splitlines()[0]
    assert results["steps"] > 0 and 0.5 < results["budget_share"] <= 1.1
    assert f"trained {results['steps']} steps" in proc.stdout and "% of the 0.2-min budget" in proc.stdout
    gt = sum(len(json.loads(p.read_text())["objects"]) for p in (out / "test").glob("[0-9]*.json"))
    assert list(results["losses"]) == ["infer_ls", "infer_scales", "infer_default"]
    for losses in results["losses"].values():
        assert set(losses["lost"]) == {"no detection", "beyond 10 cm", "within 10 cm, not 2 cm", "within 2 cm"}
        assert sum(losses["lost"].values()) == gt and "held-out instances" in proc.stdout
        bands = losses["lost_by_visibility"]
        assert list(bands) == ["< 0.1", "0.1-0.5", "0.5-0.95", ">= 0.95"] and "visible >= 0.95:" in proc.stdout
        assert {k: sum(c[k] for c in bands.values()) for k in losses["lost"]} == losses["lost"]
        assert sum(losses["lost_bop_targets"].values()) == sum(n for b, c in bands.items() if b != "< 0.1"
                                                               for n in c.values())
    assert "three working sizes" in proc.stdout and "of BOP19's targets (visible >= 0.1)" in proc.stdout
    assert set(results["cpu"]["flags"]) >= {"amx_bf16", "avx512_bf16", "avx512_vnni"}

    again = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert again.returncode == 0, again.stderr[-2000:]
    assert all(f"[{s}] done earlier, skipped" in again.stdout for s in STAGES)

    other = subprocess.run(cmd + ["--test-count", "4"], capture_output=True, text=True, timeout=60)
    assert other.returncode != 0 and "other settings (test_count)" in (other.stdout + other.stderr)


def test_cpu_description_reads_the_model_and_the_precision_flags(tmp_path, monkeypatch):
    from dope_hope.devices import cpu_description, cpu_line

    monkeypatch.delenv("ONEDNN_MAX_CPU_ISA", raising=False)
    monkeypatch.delenv("DNNL_MAX_CPU_ISA", raising=False)
    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nmodel name\t: Intel(R) Xeon(R) Platinum 8480+\n"
                    "flags\t\t: fpu avx2 avx512f avx512_vnni avx512_bf16 amx_bf16 amx_tile amx_int8\n")
    d = cpu_description(info)
    assert d["model"] == "Intel(R) Xeon(R) Platinum 8480+" and d["native_bf16"]
    assert d["flags"]["amx_bf16"] and d["flags"]["avx512_vnni"] and not d["flags"]["avx_vnni"]
    assert cpu_line(info).startswith("CPU Intel(R) Xeon(R) Platinum 8480+: amx_bf16, amx_int8, avx512_bf16")
    # oneDNN capped below its bf16 kernels (how an AMX machine stands in for an AVX2 laptop):
    # bf16 would be emulated, so the recipe is float32, and the line says why.
    monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", "avx2")
    assert not cpu_description(info)["native_bf16"]
    assert cpu_line(info).endswith("; ONEDNN_MAX_CPU_ISA=AVX2; bf16 training emulated: float32 used")
    monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", "AVX512_CORE_BF16")  # the AMD EPYC stand-in keeps bf16
    assert cpu_description(info)["native_bf16"]
    monkeypatch.delenv("ONEDNN_MAX_CPU_ISA")
    info.write_text("processor\t: 0\nmodel name\t: AMD EPYC\nflags\t\t: fpu avx2\n")
    assert cpu_line(info) == ("CPU AMD EPYC: avx2 of the precision flags (no amx_bf16, amx_int8, avx512_bf16, "
                              "avx512_vnni, avx_vnni, avx512f); bf16 training emulated: float32 used")
    assert cpu_description(tmp_path / "missing") == {"model": "unknown", "flags": dict.fromkeys(
        ("amx_bf16", "amx_int8", "avx512_bf16", "avx512_vnni", "avx_vnni", "avx512f", "avx2"), False),
        "native_bf16": False}
