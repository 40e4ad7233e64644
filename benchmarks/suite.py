"""Issue 15's benchmark: every ``edygs-synth`` scene preset × seeds × the main variants.

For each preset and seed: write the scene (``edygs-synth`` with ``SynthConfig(preset=...)``),
pose it (``edygs-process``), train the variants with ``ns-train`` — blurry-input D3DGS
(``edygs-blurry``), EDI only, + pose (``edi-events-pose``), EDyGS with the paper's losses
(``paper``) and EDyGS (ours, ``full``) — and score each run with ``edygs-eval``'s
``evaluate_run``. Training, evaluation and the per-run numbers come from
``benchmarks/ablations.py`` (``train``, ``evaluate_cached``, ``row_of``, ``VARIANTS``); this file
adds the presets, the per-preset / suite-mean tables and the issue's "done means" checks.

Writes ``OUT/results.json`` and ``OUT/results.md`` (command, machine, date): per preset and as
the mean over presets, for every variant, input-view PSNR/SSIM, PSNR inside / outside the moving
objects, novel-view PSNR/SSIM with and without per-view pose fitting, mask IoU, mean rendered
mask, ATE initial → refined and training seconds; the reference rows "EDI latent" and "blurry
input" (those images scored against the same ground truth); and the done-means table.

Layout of ``OUT``: ``PRESET/seedS/{raw,scene}`` (the scene) and ``PRESET/runs/seedS/METHOD/RUN``
(``PRESET/runs_trainT/...`` for a run with training seed T other than nerfstudio's 42).
Scenes, finished runs (``train_seconds.txt`` next to ``config.yml``) and evaluations already there
are reused, so the suite can run as several processes into one folder (e.g. one preset each)
and a last call with ``--collect-only`` writes the combined tables without training
(benchmarks/README.md).

Usage::

    OMP_NUM_THREADS=1 python benchmarks/suite.py --out /tmp/suite --seeds 0 1 --iters 3000
"""

from __future__ import annotations

import dataclasses
import json
import os
import platform
import sys
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

import tyro
from nerfstudio.utils.rich_utils import CONSOLE

sys.path.insert(0, str(Path(__file__).resolve().parent))
from ablations import (  # noqa: E402  (benchmarks/ is not a package)
    INPUT_SPLIT,
    REFERENCE_KEYS,
    TRAIN_SECONDS_FILE,
    VARIANTS,
    _device,
    _mean,
    evaluate_cached,
    row_of,
    run_config_path,
    train,
)

from edygs_ns.scripts.process import ProcessConfig, process  # noqa: E402
from edygs_ns.scripts.synth import SynthConfig, write_synthetic_scene  # noqa: E402

#: Variant labels (of ablations.VARIANTS) in the suite, in table order.
SUITE_VARIANTS: Tuple[str, ...] = ("blurry D3DGS", "EDI only", "+ pose", "+ mask (EDyGS, paper)", "+ blur (EDyGS, ours)")
BLURRY_D3DGS, POSE_VARIANT, OURS = "blurry D3DGS", "+ pose", "+ blur (EDyGS, ours)"
#: Reference rows: the EDI latents and the blurry input frames scored on the input views.
EDI_REFERENCE, BLURRY_REFERENCE = "EDI latent", "blurry input"
REFERENCES: Tuple[str, ...] = (EDI_REFERENCE, BLURRY_REFERENCE)
#: Presets of edygs-synth when edygs_ns.sim.presets does not list them (yet).
FALLBACK_PRESETS: Tuple[str, ...] = ("rigid", "two-objects", "three-objects", "articulated", "deforming", "enter-leave", "large", "static")
#: The preset of today's one-sphere scene (its path picked by SynthConfig.motion) and the one without motion.
RIGID_PRESET, STATIC_PRESET = "rigid", "static"
#: ns-train arguments of the CPU demo (scripts/demo.sh): a 64x4 deformation MLP; the default on CPU.
CPU_EXTRA_TRAIN_ARGS = "--pipeline.model.deformation.width 64 --pipeline.model.deformation.depth 4 --pipeline.model.deformation.skip-layer 2"
#: Issue 15's done-means targets (dB unless stated).
TARGET_OVER_EDI = 0.5  # EDyGS input-view PSNR - EDI latents'
TARGET_OVER_BLURRY = 2.0  # EDyGS - blurry D3DGS, every preset with motion
TARGET_INSIDE_OVER_EDI = -1.0  # inside the moving objects: EDyGS - EDI latents
TARGET_MASK_IOU = 0.6
TARGET_SUITE_OVER_BLURRY = 3.0  # mean over the suite: EDyGS - blurry D3DGS
TARGET_NOVEL_OVER_BLURRY_INPUT = 1.5  # novel views without pose fitting - the blurry input frames
TARGET_STATIC_OVER_POSE = 0.0  # no motion: EDyGS - the edi-events-pose ablation ("no worse")
STATIC_MASK_MEAN_MAX = 0.05  # no motion: mean rendered motion mask ("stays near 0")
#: Row fields that are not numbers to average.
ID_KEYS = ("preset", "seed", "motion", "train_seed")
#: nerfstudio's --machine.seed default: the training seed of a run trained without --train-seeds.
DEFAULT_TRAIN_SEED = 42


def scene_presets() -> Tuple[str, ...]:
    """edygs-synth's preset names (edygs_ns.sim.presets.SCENE_PRESETS, else FALLBACK_PRESETS)."""
    try:
        from edygs_ns.sim.presets import SCENE_PRESETS  # type: ignore[import-not-found]

        return tuple(SCENE_PRESETS)
    except ImportError:
        return FALLBACK_PRESETS


@dataclass
class SuiteBenchConfig:
    """Train and evaluate the main variants on every scene preset of edygs-synth."""

    out: Path = Path("benchmarks/results/suite")
    """output folder (scenes, runs, results.json, results.md); shared by parallel processes"""
    presets: List[str] = field(default_factory=lambda: list(scene_presets()))
    """scene presets of edygs-synth"""
    seeds: List[int] = field(default_factory=lambda: [0, 1])
    """seeds per preset (textures, motion, camera path)"""
    train_seeds: List[int] = field(default_factory=lambda: [DEFAULT_TRAIN_SEED])
    """ns-train --machine.seed of the runs; several: every scene is trained once per seed and the
    tables average them (a single run's spread is the training seed's as much as the method's)"""
    variants: List[str] = field(default_factory=lambda: list(SUITE_VARIANTS))
    """rows to run: labels of ablations.VARIANTS, or their ablation preset / method (full, paper, edygs-blurry, ...)"""
    iters: int = 3000
    """training iterations per run (the CPU demo's length)"""
    extra_train_args: Optional[str] = None
    """more ns-train arguments for every run, one quoted string; default: the CPU demo's 64x4
    deformation MLP on CPU (CPU_EXTRA_TRAIN_ARGS), nothing on CUDA"""
    device: str = "auto"
    """cpu, cuda, or auto"""
    poses: str = "colmap"
    """how scenes are posed: colmap (the paper's pipeline) or given (true poses)"""
    width: int = 128
    """synthetic scene width"""
    height: int = 96
    """synthetic scene height"""
    n_frames: int = 12
    """blurry frames per scene"""
    motions: List[str] = field(default_factory=lambda: ["circular", "circular", "bouncing"])
    """path of the rigid preset's sphere: seed s gets motions[s % len(motions)] (the README's scenes)"""
    collect_only: bool = False
    """make no scene and train nothing: tabulate the finished runs in --out (evaluating any not yet
    evaluated) and list what is missing; the merge step after parallel processes"""


def resolve_variants(names: Sequence[str]) -> List[Tuple[str, str, Any]]:
    """ablations.VARIANTS entries named by label, ablation preset or method, in VARIANTS order."""
    chosen = set()
    for name in names:
        hits = [v for v in VARIANTS if name in (v[0], v[2]) or (v[2] is None and name == v[1])]
        if not hits:
            raise ValueError(f"unknown variant {name!r}; known: {[v[0] for v in VARIANTS]} or their ablation presets")
        chosen.update(v[0] for v in hits)
    return [v for v in VARIANTS if v[0] in chosen]


def extra_train_args(cfg: SuiteBenchConfig) -> str:
    """The ns-train arguments added to every run (CPU_EXTRA_TRAIN_ARGS on CPU unless given)."""
    if cfg.extra_train_args is not None:
        return cfg.extra_train_args
    return CPU_EXTRA_TRAIN_ARGS if _device(cfg.device) == "cpu" else ""


def motion_of(cfg: SuiteBenchConfig, preset: str, seed: int) -> Optional[str]:
    """The sphere path of the rigid preset's scene ``seed`` (None for the other presets)."""
    return cfg.motions[seed % len(cfg.motions)] if preset == RIGID_PRESET else None


def scene_root(cfg: SuiteBenchConfig, preset: str, seed: int) -> Path:
    return cfg.out / preset / f"seed{seed}"


def runs_root(cfg: SuiteBenchConfig, preset: str, train_seed: int) -> Path:
    """Where the runs of ``preset`` with training seed ``train_seed`` go (see the layout above)."""
    return cfg.out / preset / ("runs" if train_seed == DEFAULT_TRAIN_SEED else f"runs_train{train_seed}")


def with_train_seed(run_cfg: SuiteBenchConfig, train_seed: int) -> SuiteBenchConfig:
    """``run_cfg`` whose runs train with ``train_seed`` (its ns-train arguments as they are for 42)."""
    if train_seed == DEFAULT_TRAIN_SEED:
        return run_cfg
    return dataclasses.replace(run_cfg, extra_train_args=f"{run_cfg.extra_train_args or ''} --machine.seed {train_seed}".strip())


def synth_config(cfg: SuiteBenchConfig, preset: str, seed: int, raw: Path) -> SynthConfig:
    """edygs-synth's config of one suite scene."""
    kwargs: Dict[str, Any] = dict(output_dir=raw, seed=seed, width=cfg.width, height=cfg.height, n_frames=cfg.n_frames, overwrite=True)
    motion = motion_of(cfg, preset, seed)
    if motion is not None:
        kwargs["motion"] = motion
    if "preset" in {f.name for f in dataclasses.fields(SynthConfig)}:
        kwargs["preset"] = preset
    elif preset != RIGID_PRESET:
        raise ValueError(f"edygs-synth has no scene presets yet (SynthConfig.preset); only {RIGID_PRESET!r} can be made")
    return SynthConfig(**kwargs)


def make_scene(cfg: SuiteBenchConfig, preset: str, seed: int) -> Path:
    """Raw capture + processed scene of (preset, seed), reused when there and made the same way."""
    root = scene_root(cfg, preset, seed)
    raw, scene = root / "raw", root / "scene"
    if (raw / "scene.json").exists():
        summary = json.loads((raw / "scene.json").read_text())
        written = summary["config"]
        made_preset = summary.get("preset", written.get("preset", RIGID_PRESET))  # scenes from before presets: rigid
        motion = motion_of(cfg, preset, seed)
        if made_preset != preset or (motion is not None and written.get("motion") != motion):
            raise ValueError(f"{raw}: scene was made with preset {made_preset!r}, motion {written.get('motion')!r}; "
                             f"this run asks for {preset!r}, {motion!r} (another --out?)")
    if (scene / "transforms.json").exists():
        return scene
    if not (raw / "exposures.csv").exists():
        write_synthetic_scene(synth_config(cfg, preset, seed, raw))
    config = ProcessConfig(output=scene, poses=cfg.poses)  # type: ignore[arg-type]
    config.inputs.exposures = raw / "exposures.csv"
    config.inputs.events = raw / "events.h5"
    process(config)
    return scene


def reference_row(metrics: Dict[str, Any], label: str) -> Optional[Dict[str, Any]]:
    """Reference ``label``'s input-view numbers in a run's metrics, keyed like row_of (input_psnr, ...)."""
    values = metrics.get(label, {}).get(INPUT_SPLIT)
    if not values:
        return None
    out = {}
    for key in REFERENCE_KEYS:
        value = _mean(values.get(key))
        out[f"input_{key}"] = value if isinstance(value, (int, float)) else None
    return out


# ----------------------------------------------------------------------------- tables


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def mean_row(rows: Sequence[Dict[str, Any]]) -> Dict[str, Any]:
    """Mean of every numeric field over ``rows`` (None where no row has a number); "n": row count."""
    keys = [k for k in dict.fromkeys(k for r in rows for k in r) if k not in ID_KEYS]
    out: Dict[str, Any] = {}
    for key in keys:
        values = [r[key] for r in rows if _number(r.get(key))]
        out[key] = sum(values) / len(values) if values else None
    out["n"] = len(rows)
    return out


def per_preset(results: Dict[str, Any]) -> Dict[str, Dict[str, Dict[str, Any]]]:
    """{preset: {variant or reference label: mean over that preset's seeds}}, presets in run order."""
    table: Dict[str, Dict[str, Dict[str, Any]]] = {}
    groups = list(results["rows"].items()) + list(results.get("references", {}).items())
    presets = list(dict.fromkeys(r["preset"] for _, rows in groups for r in rows))
    for preset in presets:
        table[preset] = {}
        for label, rows in groups:
            mine = [r for r in rows if r["preset"] == preset]
            if mine:
                table[preset][label] = mean_row(mine)
    return table


def suite_mean(table: Dict[str, Dict[str, Dict[str, Any]]]) -> Dict[str, Dict[str, Any]]:
    """{label: mean over presets of the per-preset means} (each preset weighs the same; "n": presets)."""
    labels = list(dict.fromkeys(label for rows in table.values() for label in rows))
    return {label: mean_row([rows[label] for rows in table.values() if label in rows]) for label in labels}


def is_static(rows: Dict[str, Dict[str, Any]], preset: str) -> bool:
    """A preset without moving objects: named so, or no view has a pixel inside a ground-truth mask
    (no PSNR inside the objects for any row, while some row has a PSNR)."""
    if preset == STATIC_PRESET:
        return True
    has_psnr = any(_number(r.get("input_psnr")) for r in rows.values())
    return has_psnr and not any(_number(r.get("input_psnr_dynamic")) for r in rows.values())


def _get(rows: Dict[str, Dict[str, Any]], label: str, key: str) -> Optional[float]:
    value = rows.get(label, {}).get(key)
    return value if _number(value) else None


def _diff(a: Optional[float], b: Optional[float]) -> Optional[float]:
    return None if a is None or b is None else a - b


def _check(scope: str, name: str, value: Optional[float], target: float, at_least: bool = True, signed: bool = True) -> Dict[str, Any]:
    """One done-means check; ``pass`` is None when a number is missing. ``signed``: a difference (dB)."""
    ok = None if value is None else (value >= target if at_least else value <= target)
    text = ("≥ " if at_least else "≤ ") + (f"{target:+g}" if signed else f"{target:g}")
    return {"preset": scope, "check": name, "value": value, "target": text, "pass": ok}


def done_checks(table: Dict[str, Dict[str, Dict[str, Any]]], mean: Optional[Dict[str, Dict[str, Any]]] = None) -> List[Dict[str, Any]]:
    """Issue 15's done-means checks on the per-preset means (and the suite mean when given)."""
    checks: List[Dict[str, Any]] = []
    for preset, rows in table.items():
        ours_in = _get(rows, OURS, "input_psnr")
        if is_static(rows, preset):
            checks.append(_check(preset, "no motion: rendered mask mean (EDyGS)", _get(rows, OURS, "input_mask_mean"),
                                 STATIC_MASK_MEAN_MAX, at_least=False, signed=False))
            checks.append(_check(preset, "no motion: EDyGS − + pose (in PSNR)", _diff(ours_in, _get(rows, POSE_VARIANT, "input_psnr")),
                                 TARGET_STATIC_OVER_POSE))
        else:
            checks.append(_check(preset, "EDyGS − EDI latents (in PSNR)", _diff(ours_in, _get(rows, EDI_REFERENCE, "input_psnr")), TARGET_OVER_EDI))
            checks.append(_check(preset, "EDyGS − blurry D3DGS (in PSNR)", _diff(ours_in, _get(rows, BLURRY_D3DGS, "input_psnr")), TARGET_OVER_BLURRY))
            checks.append(_check(preset, "inside objects: EDyGS − EDI latents",
                                 _diff(_get(rows, OURS, "input_psnr_dynamic"), _get(rows, EDI_REFERENCE, "input_psnr_dynamic")),
                                 TARGET_INSIDE_OVER_EDI))
            checks.append(_check(preset, "mask IoU (EDyGS)", _get(rows, OURS, "input_mask_iou"), TARGET_MASK_IOU, signed=False))
        checks.append(_check(preset, "novel, no pose fit: EDyGS − blurry input frames",
                             _diff(_get(rows, OURS, "novel_nofit_psnr"), _get(rows, BLURRY_REFERENCE, "input_psnr")),
                             TARGET_NOVEL_OVER_BLURRY_INPUT))
    if mean:
        checks.append(_check("suite mean", "EDyGS − blurry D3DGS (in PSNR)",
                             _diff(_get(mean, OURS, "input_psnr"), _get(mean, BLURRY_D3DGS, "input_psnr")), TARGET_SUITE_OVER_BLURRY))
        checks.append(_check("suite mean", "novel, no pose fit: EDyGS − blurry input frames",
                             _diff(_get(mean, OURS, "novel_nofit_psnr"), _get(mean, BLURRY_REFERENCE, "input_psnr")),
                             TARGET_NOVEL_OVER_BLURRY_INPUT))
        # the same target under the anchored protocol (each camera placed by its nearest training latent)
        checks.append(_check("suite mean", "novel, anchored: EDyGS − blurry input frames",
                             _diff(_get(mean, OURS, "novel_anchor_psnr"), _get(mean, BLURRY_REFERENCE, "input_psnr")),
                             TARGET_NOVEL_OVER_BLURRY_INPUT))
    return checks


def _fmt(value: Any, digits: int) -> str:
    return f"{value:.{digits}f}" if _number(value) else "-"


#: (header, row key, digits) of the per-preset and suite-mean tables, after the label columns.
COLUMNS: Tuple[Tuple[str, str, int], ...] = (
    ("in PSNR↑", "input_psnr", 2),
    ("in SSIM↑", "input_ssim", 4),
    ("in PSNR inside↑", "input_psnr_dynamic", 2),
    ("in PSNR outside↑", "input_psnr_static", 2),
    ("novel PSNR (pose fit)↑", "novel_psnr", 2),
    ("novel SSIM (pose fit)↑", "novel_ssim", 4),
    ("novel PSNR (no fit)↑", "novel_nofit_psnr", 2),
    ("novel SSIM (no fit)↑", "novel_nofit_ssim", 4),
    ("novel PSNR seen (no fit)↑", "novel_nofit_psnr_covisible", 2),
    ("novel error share unseen (no fit)", "novel_nofit_unseen_error_share", 2),
    ("novel PSNR (anchored)↑", "novel_anchor_psnr", 2),
    ("novel PSNR seen (anchored)↑", "novel_anchor_psnr_covisible", 2),
    ("mask IoU↑", "input_mask_iou", 3),
    ("mask mean", "input_mask_mean", 3),
)


def _cells(row: Dict[str, Any]) -> List[str]:
    cells = [_fmt(row.get(key), digits) for _, key, digits in COLUMNS]
    ate_a, ate_b = row.get("ate_initial"), row.get("ate_refined")
    cells.append("-" if not (_number(ate_a) or _number(ate_b)) else f"{_fmt(ate_a, 4)} → {_fmt(ate_b, 4)}")
    cells.append(_fmt(row.get("train_seconds"), 0))
    return cells


def _header(first: Sequence[str]) -> List[str]:
    names = list(first) + [h for h, _, _ in COLUMNS] + ["ATE init → refined", "train s"]
    return ["| " + " | ".join(names) + " |", "|" + " --- |" * len(names)]


def markdown(results: Dict[str, Any]) -> str:
    """The per-preset table, the suite means and the done-means checks."""
    table, mean, checks = results["per_preset"], results["suite_mean"], results["checks"]
    order = list(results["rows"]) + [r for r in REFERENCES if any(r in rows for rows in table.values())]
    lines = ["## Per preset (mean over the runs: seeds × training seeds)", ""] + _header(["Preset", "Variant", "runs"])
    for preset, rows in table.items():
        for label in order:
            if label in rows:
                lines.append(f"| {preset} | {label} | {rows[label]['n']} | " + " | ".join(_cells(rows[label])) + " |")
    lines += ["", f"## Suite mean (mean over {len(table)} presets of the per-preset means)", ""] + _header(["Variant", "presets"])
    for label in order:
        if label in mean:
            lines.append(f"| {label} | {mean[label]['n']} | " + " | ".join(_cells(mean[label])) + " |")
    lines += ["", "## Done means (issue 15)", "", "| Preset | Check | Value | Target | Met |", "| --- | --- | --- | --- | --- |"]
    for c in checks:
        met = "-" if c["pass"] is None else ("yes" if c["pass"] else "**no**")
        value = "-" if c["value"] is None else f"{c['value']:+.3f}"
        lines.append(f"| {c['preset']} | {c['check']} | {value} | {c['target']} | {met} |")
    lines += ["", "Novel views: \"pose fit\" fits each novel camera's pose to its image with the model frozen "
              "(edygs_ns/eval/novel_pose_fit.py); \"no fit\" renders the true novel cameras mapped into the run's frame "
              "by the similarity fitted on the training cameras only. Inside / outside: PSNR over the ground-truth "
              "moving-object masks and the rest (\"-\" where a scene has no moving pixel). Mask mean: mean rendered "
              "motion mask on the input views. Reference rows score the images themselves."]
    if results.get("missing"):
        lines += ["", "Not in this table (not trained / not finished): " + ", ".join(results["missing"])]
    if results.get("failures"):
        lines += ["", "Failed: " + "; ".join(results["failures"])]
    return "\n".join(lines)


def summarise(results: Dict[str, Any]) -> Dict[str, Any]:
    """Add per_preset, suite_mean and checks to ``results`` (rows and references filled)."""
    results["per_preset"] = per_preset(results)
    results["suite_mean"] = suite_mean(results["per_preset"])
    results["checks"] = done_checks(results["per_preset"], results["suite_mean"])
    return results


# ----------------------------------------------------------------------------- running


def main(cfg: SuiteBenchConfig) -> Dict[str, Any]:
    chosen = resolve_variants(cfg.variants)
    if not cfg.collect_only:  # fail before training anything if a preset cannot be made
        for preset in cfg.presets:
            synth_config(cfg, preset, 0, cfg.out / "unused")
    extra = extra_train_args(cfg)
    if cfg.extra_train_args is None and extra:
        CONSOLE.log(f"[suite] device is CPU: every run gets the CPU demo's deformation MLP ({extra}); pass --extra-train-args '' to train the default one")
    run_cfg = dataclasses.replace(cfg, extra_train_args=extra)
    cfg.out.mkdir(parents=True, exist_ok=True)
    results: Dict[str, Any] = {
        "command": " ".join([Path(sys.argv[0]).name] + sys.argv[1:]),
        "machine": f"{platform.node()} {platform.processor() or platform.machine()}, {os.cpu_count()} cores, device {_device(cfg.device)}",
        "date": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "config": {k: str(v) for k, v in vars(run_cfg).items()},
        "rows": {label: [] for label, _, _ in chosen},
        "references": {label: [] for label in REFERENCES},
        "missing": [],
        "failures": [],
    }
    for preset in cfg.presets:
        for seed in cfg.seeds:
            tag = f"{preset}/seed{seed}"
            scene = scene_root(cfg, preset, seed) / "scene"
            if cfg.collect_only and not (scene / "transforms.json").exists():
                results["missing"].append(f"{tag} (no scene)")
                continue
            if not cfg.collect_only:
                scene = make_scene(cfg, preset, seed)
            found_refs = set()
            for train_seed in cfg.train_seeds:
                runs = runs_root(cfg, preset, train_seed)
                seeded_cfg = with_train_seed(run_cfg, train_seed)
                run_tag = tag if train_seed == DEFAULT_TRAIN_SEED else f"{tag} (training seed {train_seed})"
                for label, method, ablation in chosen:
                    config_path = run_config_path(scene, label, method, runs)
                    if cfg.collect_only and not (config_path.parent / TRAIN_SECONDS_FILE).exists():
                        results["missing"].append(f"{run_tag} {label}")
                        continue
                    try:
                        config_path, seconds = train(seeded_cfg, scene, label, method, ablation, runs)
                    except RuntimeError as exc:
                        CONSOLE.log(f"[red][suite] {exc}")
                        results["failures"].append(f"{run_tag} {label}: {exc}")
                        continue
                    metrics = evaluate_cached(config_path, label)
                    row = row_of(metrics, label, seconds)
                    row.update(preset=preset, seed=seed, motion=motion_of(cfg, preset, seed), train_seed=train_seed)
                    results["rows"][label].append(row)
                    for ref in REFERENCES:  # the same images for every run of the scene: keep the first
                        ref_row = None if ref in found_refs else reference_row(metrics, ref)
                        if ref_row is not None:
                            found_refs.add(ref)
                            results["references"][ref].append(dict(ref_row, preset=preset, seed=seed, motion=row["motion"]))
    results["references"] = {k: v for k, v in results["references"].items() if v}
    summarise(results)
    table = markdown(results)
    (cfg.out / "results.json").write_text(json.dumps(results, indent=2))
    (cfg.out / "results.md").write_text(
        f"Command: `{results['command']}`  \nMachine: {results['machine']}  \nDate: {results['date']}  \n"
        f"Iterations: {cfg.iters}; extra ns-train arguments: `{extra or '(none)'}`\n\n{table}\n"
    )
    CONSOLE.print(table, markup=False, highlight=False, soft_wrap=True)
    return results


if __name__ == "__main__":
    main(tyro.cli(SuiteBenchConfig))
