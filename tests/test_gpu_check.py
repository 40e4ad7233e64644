"""scripts/gpu_check.sh's dry mode (--device cpu, tiny sizes) end to end: every stage runs and
gpu_check.json / gpu_check.md are written (the GPU run's plumbing, checked without a GPU)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))

import gpu_check  # noqa: E402


def test_short_run_shape_resets_after_the_switch_and_refines_after_it():
    for iters in (40, 1500, 20000):
        args = gpu_check.short_run_shape(iters)
        every, reset = int(args[1]), int(args[3])
        assert 0.4 * iters < reset < 0.75 * iters - every and reset % every == 0


def test_dry_mode_writes_json_and_markdown(tmp_path):
    cfg = gpu_check.GpuCheckConfig(out=tmp_path / "gc", device="cpu", train_iters=30, bench_iters=12,
                                      bench_parallel=True, results=tmp_path / "kept")
    data = gpu_check.main(cfg)
    out = tmp_path / "gc"
    written = json.loads((out / "gpu_check.json").read_text())
    assert written["dry_run"] and written["ok"], json.dumps(written["stages"], default=str)[:3000]
    stages = written["stages"]
    assert set(stages) == set(gpu_check.STAGES) and all(s["status"] == "ok" for s in stages.values())
    assert stages["parity"]["tests"] >= 3  # collected; on CPU they skip
    train = stages["train"]
    assert all(train["checks"].values()) and train["switch_step"] < train["reset_steps"][0]
    assert train["command"].startswith("ns-train edygs ") and "--machine.device-type cpu" in train["command"]
    assert stages["render"]["frames"] == 4 and "input_psnr" in stages["eval"]
    runs = stages["bench"]["runs"]
    assert set(runs) == {"blurry D3DGS", "EDyGS"} and all(r["train_seconds"] > 0 and "input_psnr" in r for r in runs.values())
    md = (out / "gpu_check.md").read_text()
    assert md.startswith("# GPU check (dry mode, CPU)") and "| bench | ok |" in md and "## Benchmark: 48x36" in md
    assert "edygs-doctor" in md and data["ok"]
    assert (tmp_path / "kept" / "gpu_check.md").read_text() == md  # the --results copy, final too
