"""benchmarks/suite.py's tables on hand-made rows: means per preset and over the suite, the
done-means checks, a scene without motion (no PSNR inside objects), and variant selection.
No training: the rows stand in for what row_of reads from evaluate_run's metrics."""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path
from typing import Any, Dict, Optional

import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.fixture(scope="module")
def suite():
    spec = importlib.util.spec_from_file_location("suite_bench", BENCHMARKS / "suite.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["suite_bench"] = module
    spec.loader.exec_module(module)
    return module


def _row(preset: str, seed: int, psnr: float, dyn: Optional[float], iou: Optional[float] = None,
         mask_mean: Optional[float] = None, nofit: Optional[float] = None) -> Dict[str, Any]:
    return {"preset": preset, "seed": seed, "motion": None, "input_psnr": psnr, "input_ssim": 0.8, "input_psnr_dynamic": dyn,
            "input_psnr_static": psnr + 1.0, "input_mask_iou": iou, "input_mask_mean": mask_mean, "novel_psnr": psnr - 1.0,
            "novel_nofit_psnr": nofit, "ate_initial": 0.04, "ate_refined": 0.02, "train_seconds": 100.0 + seed}


def _ref(preset: str, seed: int, psnr: float, dyn: Optional[float]) -> Dict[str, Any]:
    return {"preset": preset, "seed": seed, "motion": None, "input_psnr": psnr, "input_ssim": 0.7,
            "input_psnr_dynamic": dyn, "input_psnr_static": psnr}


def _results(suite) -> Dict[str, Any]:
    """Two presets × two seeds: "two-objects" with motion, "static" with empty masks (dyn None)."""
    return {
        "rows": {
            suite.BLURRY_D3DGS: [_row("two-objects", 0, 25.0, 19.0), _row("two-objects", 1, 27.0, 21.0),
                                 _row("static", 0, 30.0, None), _row("static", 1, 32.0, None)],
            suite.POSE_VARIANT: [_row("two-objects", 0, 27.0, 20.0), _row("static", 0, 31.0, None), _row("static", 1, 33.0, None)],
            suite.OURS: [_row("two-objects", 0, 29.0, 23.0, iou=0.7, mask_mean=0.1, nofit=26.0),
                         _row("two-objects", 1, 30.0, 25.0, iou=0.5, mask_mean=0.2, nofit=27.0),
                         _row("static", 0, 31.5, None, iou=1.0, mask_mean=0.01, nofit=30.0),
                         _row("static", 1, 32.5, None, iou=None, mask_mean=0.03, nofit=31.0)],
        },
        "references": {
            suite.EDI_REFERENCE: [_ref("two-objects", 0, 28.0, 24.5), _ref("two-objects", 1, 28.4, 25.5),
                                  _ref("static", 0, 29.0, None), _ref("static", 1, 29.0, None)],
            suite.BLURRY_REFERENCE: [_ref("two-objects", 0, 24.0, 18.0), _ref("two-objects", 1, 26.0, 20.0),
                                     _ref("static", 0, 27.0, None), _ref("static", 1, 27.0, None)],
        },
    }


def test_mean_row_skips_missing_values(suite):
    mean = suite.mean_row([{"preset": "a", "seed": 0, "x": 1.0, "y": None}, {"preset": "a", "seed": 1, "x": 3.0, "y": None, "z": 5.0}])
    assert mean == {"x": 2.0, "y": None, "z": 5.0, "n": 2}
    assert "preset" not in mean and "seed" not in mean


def test_per_preset_and_suite_means(suite):
    results = suite.summarise(_results(suite))
    table, mean = results["per_preset"], results["suite_mean"]
    assert list(table) == ["two-objects", "static"]
    ours = table["two-objects"][suite.OURS]
    assert ours["n"] == 2 and ours["input_psnr"] == pytest.approx(29.5) and ours["input_psnr_dynamic"] == pytest.approx(24.0)
    assert ours["input_mask_iou"] == pytest.approx(0.6) and ours["train_seconds"] == pytest.approx(100.5)
    assert table["two-objects"][suite.POSE_VARIANT]["n"] == 1
    # a scene whose masks are all empty has no PSNR inside objects: None, not a crash or a zero
    assert table["static"][suite.OURS]["input_psnr_dynamic"] is None
    assert table["static"][suite.OURS]["input_mask_iou"] == pytest.approx(1.0)  # the one view with a value
    # the suite mean weighs each preset the same (mean of per-preset means)
    assert mean[suite.OURS]["n"] == 2
    assert mean[suite.OURS]["input_psnr"] == pytest.approx((29.5 + 32.0) / 2)
    assert mean[suite.OURS]["input_psnr_dynamic"] == pytest.approx(24.0)  # only the preset with motion has one
    assert mean[suite.EDI_REFERENCE]["input_psnr"] == pytest.approx((28.2 + 29.0) / 2)


def test_done_checks(suite):
    results = suite.summarise(_results(suite))
    checks = {(c["preset"], c["check"]): c for c in results["checks"]}

    def check(preset: str, start: str) -> Dict[str, Any]:
        (hit,) = [c for (p, name), c in checks.items() if p == preset and name.startswith(start)]
        return hit

    over_edi = check("two-objects", "EDyGS − EDI")
    assert over_edi["value"] == pytest.approx(29.5 - 28.2) and over_edi["pass"] is True
    over_blurry = check("two-objects", "EDyGS − blurry D3DGS")
    assert over_blurry["value"] == pytest.approx(29.5 - 26.0) and over_blurry["pass"] is True
    inside = check("two-objects", "inside objects")
    assert inside["value"] == pytest.approx(24.0 - 25.0) and inside["pass"] is True  # exactly at the -1 dB target
    assert check("two-objects", "mask IoU")["pass"] is True  # 0.6 meets >= 0.6
    novel = check("two-objects", "novel, no pose fit")
    assert novel["value"] == pytest.approx(26.5 - 25.0) and novel["pass"] is True
    # the preset without motion gets its own checks instead of the motion ones
    assert not [c for (p, name), c in checks.items() if p == "static" and name.startswith(("inside", "mask IoU", "EDyGS − EDI"))]
    mask_mean = check("static", "no motion: rendered mask mean")
    assert mask_mean["value"] == pytest.approx(0.02) and mask_mean["pass"] is True
    vs_pose = check("static", "no motion: EDyGS − + pose")
    assert vs_pose["value"] == pytest.approx(32.0 - 32.0) and vs_pose["pass"] is True
    suite_blurry = check("suite mean", "EDyGS − blurry D3DGS")
    assert suite_blurry["value"] == pytest.approx((29.5 + 32.0) / 2 - (26.0 + 31.0) / 2) and suite_blurry["pass"] is False


def test_missing_numbers_leave_checks_open(suite):
    """A variant not run gives no value: the check is neither met nor failed, and the table says "-"."""
    results = _results(suite)
    del results["rows"][suite.BLURRY_D3DGS]
    results = suite.summarise(results)
    blurry = [c for c in results["checks"] if "blurry D3DGS" in c["check"]]
    assert blurry and all(c["value"] is None and c["pass"] is None for c in blurry)
    text = suite.markdown(results)
    assert "| two-objects | EDyGS − blurry D3DGS (in PSNR) | - | ≥ +2 | - |" in text


def test_markdown_rows(suite):
    results = suite.summarise(_results(suite))
    text = suite.markdown(results)
    lines = text.splitlines()
    ours_static = [line for line in lines if line.startswith(f"| static | {suite.OURS} |")]
    assert len(ours_static) == 1
    cells = [c.strip() for c in ours_static[0].strip("|").split("|")]
    header = [c.strip() for c in lines[2].strip("|").split("|")]
    by_name = dict(zip(header, cells))
    assert by_name["runs"] == "2" and by_name["in PSNR↑"] == "32.00" and by_name["in PSNR inside↑"] == "-"
    assert by_name["ATE init → refined"] == "0.0400 → 0.0200" and by_name["mask mean"] == "0.020"
    # the reference rows come after the variants in every preset, and appear in the suite mean
    per_preset = lines[: lines.index(next(line for line in lines if line.startswith("## Suite mean")))]
    static_labels = [c.split("|")[2].strip() for c in per_preset if c.startswith("| static |")]
    assert static_labels == [suite.BLURRY_D3DGS, suite.POSE_VARIANT, suite.OURS, suite.EDI_REFERENCE, suite.BLURRY_REFERENCE]
    assert any(line.startswith(f"| {suite.EDI_REFERENCE} | 2 |") for line in lines)
    assert "| suite mean | EDyGS − blurry D3DGS (in PSNR) | +2.250 | ≥ +3 | **no** |" in text
    assert not any("nan" in line for line in lines)


def test_static_detected_from_empty_masks(suite):
    rows = {suite.OURS: {"input_psnr": 30.0, "input_psnr_dynamic": None}, suite.EDI_REFERENCE: {"input_psnr": 29.0, "input_psnr_dynamic": None}}
    assert suite.is_static(rows, "some-new-preset")
    assert not suite.is_static({suite.OURS: {"input_psnr": 30.0, "input_psnr_dynamic": 20.0}}, "rigid")
    assert not suite.is_static({}, "rigid")  # nothing measured yet is not "no motion"
    assert suite.is_static({}, suite.STATIC_PRESET)


def test_variant_selection(suite):
    labels = [v[0] for v in suite.resolve_variants(["full", "blurry D3DGS", "edi-events-pose", "edygs-blurry"])]
    assert labels == [suite.BLURRY_D3DGS, suite.POSE_VARIANT, suite.OURS]  # VARIANTS order, no duplicates
    assert [v[0] for v in suite.resolve_variants(list(suite.SUITE_VARIANTS))] == list(suite.SUITE_VARIANTS)
    with pytest.raises(ValueError, match="unknown variant"):
        suite.resolve_variants(["nope"])


def test_cpu_gets_the_demo_mlp(suite):
    assert suite.extra_train_args(suite.SuiteBenchConfig(device="cpu")) == suite.CPU_EXTRA_TRAIN_ARGS
    assert suite.extra_train_args(suite.SuiteBenchConfig(device="cuda")) == ""
    assert suite.extra_train_args(suite.SuiteBenchConfig(device="cpu", extra_train_args="")) == ""


def test_reference_row_reads_evaluate_run_metrics(suite):
    metrics = {suite.EDI_REFERENCE: {suite.INPUT_SPLIT: {"psnr": {"mean": 28.0, "std": 1.0, "n": 4}, "ssim": {"mean": 0.9},
                                                          "psnr_static": {"mean": 29.0}}}}
    ref = suite.reference_row(metrics, suite.EDI_REFERENCE)
    assert ref == {"input_psnr": 28.0, "input_ssim": 0.9, "input_psnr_dynamic": None, "input_psnr_static": 29.0}
    assert suite.reference_row(metrics, suite.BLURRY_REFERENCE) is None
    assert not math.isnan(ref["input_psnr"])


def test_training_seeds_get_their_own_runs_and_are_averaged(suite, tmp_path):
    import json

    cfg = suite.SuiteBenchConfig(out=tmp_path, extra_train_args="--x 1")
    assert suite.runs_root(cfg, "rigid", suite.DEFAULT_TRAIN_SEED) == tmp_path / "rigid" / "runs"  # as before train seeds
    assert suite.runs_root(cfg, "rigid", 7) == tmp_path / "rigid" / "runs_train7"
    assert suite.with_train_seed(cfg, suite.DEFAULT_TRAIN_SEED).extra_train_args == "--x 1"
    assert suite.with_train_seed(cfg, 7).extra_train_args == "--x 1 --machine.seed 7"
    # two training seeds of one scene: two rows, both in the preset's mean, both kept by the merge
    rows = [dict(_row("two-objects", 0, 28.0, 22.0), train_seed=42), dict(_row("two-objects", 0, 30.0, 24.0), train_seed=7)]
    results = suite.summarise({"rows": {suite.OURS: rows}, "references": {}})
    assert results["per_preset"]["two-objects"][suite.OURS]["input_psnr"] == pytest.approx(29.0)
    assert results["per_preset"]["two-objects"][suite.OURS]["n"] == 2 and "train_seed" not in results["per_preset"]["two-objects"][suite.OURS]
    spec = importlib.util.spec_from_file_location("suite_merge", BENCHMARKS / "suite_merge.py")
    merge_module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(merge_module)
    (tmp_path / "a.json").write_text(json.dumps({"command": "a", "rows": {suite.OURS: rows[:1]}, "references": {}}))
    (tmp_path / "b.json").write_text(json.dumps({"command": "b", "rows": {suite.OURS: rows[1:]}, "references": {}}))
    merged = merge_module.merge([tmp_path / "a.json", tmp_path / "b.json"])
    assert sorted(r["train_seed"] for r in merged["rows"][suite.OURS]) == [7, 42]


def test_merge_keeps_the_later_run_of_each_row(suite, tmp_path):
    import json

    spec = importlib.util.spec_from_file_location("suite_merge", BENCHMARKS / "suite_merge.py")
    merge_module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(merge_module)
    old = {"command": "old", "date": "d1", "rows": {"EDyGS": [_row("two-objects", 0, 28.0, 22.0), _row("two-objects", 1, 29.0, 23.0)]},
           "references": {"EDI latent": [_ref("two-objects", 0, 27.0, 21.0)]}}
    new = {"command": "new", "date": "d2", "rows": {"EDyGS": [_row("two-objects", 1, 30.0, 24.0)], "blurry D3DGS": [_row("static", 0, 26.0, None)]},
           "references": {}}
    (tmp_path / "old.json").write_text(json.dumps(old))
    (tmp_path / "new.json").write_text(json.dumps(new))
    merged = merge_module.merge([tmp_path / "old.json", tmp_path / "new.json"])
    rows = {(r["preset"], r["seed"]): r for r in merged["rows"]["EDyGS"]}
    assert rows[("two-objects", 1)]["input_psnr"] == 30.0 and rows[("two-objects", 1)]["source"].endswith("new.json")
    assert rows[("two-objects", 0)]["source"].endswith("old.json")
    assert merged["per_preset"]["two-objects"]["EDyGS"]["input_psnr"] == pytest.approx(29.0)  # (28 + 30) / 2
    assert merged["per_preset"]["static"]["blurry D3DGS"]["n"] == 1
    assert [s["command"] for s in merged["sources"]] == ["old", "new"]
    (tmp_path / "bad.json").write_text("{}")
    with pytest.raises(SystemExit, match="bad.json"):
        merge_module.merge([tmp_path / "bad.json"])
