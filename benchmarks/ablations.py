"""The paper's Table 1 / Table 2 shape on the built-in synthetic scenes, one command.

For each seed: write the synthetic scene (``edygs-synth``), pose it (``edygs-process``: COLMAP on
the EDI latents, or the true poses with ``--poses given``), then train every variant with
``ns-train`` — the blurry-input deformable-3DGS baseline (``edygs-blurry``) and the ablation
presets (events-only, EDI-only, EDI+events, +pose, +mask = EDyGS with the paper's losses, + our
blur loss = the default EDyGS) — and evaluate each run
with ``edygs-eval``'s ``evaluate_run``. Writes ``OUT/results.json`` and ``OUT/results.md``
(input-view and novel-view PSNR/SSIM/LPIPS, mask IoU, ATE before/after, training time) with the
command, machine and date that produced them.

Usage::

    OMP_NUM_THREADS=1 python benchmarks/ablations.py --out benchmarks/results/cpu --seeds 0 1 2 --iters 3000

Scenes, runs and evaluations already in ``--out`` are reused, so seeds can train as separate
processes (one per core) into the same folder and a last call over all seeds writes the combined
table without training or evaluating again.
"""

from __future__ import annotations

import json
import os
import platform
import shlex
import subprocess
import sys
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Dict, List, Tuple

import tyro
from nerfstudio.utils.rich_utils import CONSOLE

from edygs_ns.configs.run_length import run_length_args
from edygs_ns.eval.evaluate import (COVISIBILITY_KEYS, INPUT_SPLIT, NOVEL_ANCHORED_SPLIT, NOVEL_SPLIT, NOVEL_UNFITTED_SPLIT,
                                   REGION_PSNR_KEYS, evaluate_run)
from edygs_ns.preprocess.pipeline import ProcessConfig, process
from edygs_ns.sim.writer import SynthConfig, write_synthetic_scene

#: (row label, ns-train method, ablation preset or None) in the paper's table order.
VARIANTS: Tuple[Tuple[str, str, Any], ...] = (
    ("blurry D3DGS", "edygs-blurry", None),
    ("events only", "edygs", "events-only"),
    ("EDI only", "edygs", "edi-only"),
    ("EDI + events", "edygs", "edi-events"),
    ("+ pose", "edygs", "edi-events-pose"),
    ("+ mask (EDyGS, paper)", "edygs", "paper"),
    ("+ blur (EDyGS, ours)", "edygs", "full"),
)
#: Numbers kept for the reference images (EDI latents, blurry frames) scored on the input views.
REFERENCE_KEYS = ("psnr", "ssim", "psnr_dynamic", "psnr_static")


@dataclass
class AblationBenchConfig:
    """Train and evaluate every variant on synthetic scenes."""

    out: Path = Path("benchmarks/results/cpu")
    """output folder (scenes, runs, results.json, results.md)"""
    seeds: List[int] = field(default_factory=lambda: [0, 1, 2])
    """synthetic scenes (seed picks textures, object motion and camera path)"""
    iters: int = 3000
    """training iterations per run (the CPU demo's length)"""
    poses: str = "colmap"
    """how scenes are posed: colmap (the paper's pipeline) or given (true poses)"""
    variants: List[str] = field(default_factory=lambda: [v[0] for v in VARIANTS])
    """which rows to run (labels of VARIANTS)"""
    device: str = "auto"
    """cpu, cuda, or auto"""
    width: int = 128
    """synthetic scene width"""
    height: int = 96
    """synthetic scene height"""
    n_frames: int = 12
    """blurry frames per scene"""
    motions: List[str] = field(default_factory=lambda: ["circular", "bouncing", "linear"])
    """sphere motion of each scene: seed s gets motions[s % len(motions)] (circular, linear, bouncing)"""
    extra_train_args: str = ""
    """more ns-train arguments passed to every run, one quoted string (e.g. a smaller deformation
    MLP on CPU: "--pipeline.model.deformation.width 64")"""


def _device(name: str) -> str:
    if name != "auto":
        return name
    import torch

    return "cuda" if torch.cuda.is_available() else "cpu"


def motion_of(cfg: AblationBenchConfig, seed: int) -> str:
    """The sphere motion of scene ``seed``."""
    return cfg.motions[seed % len(cfg.motions)]


def make_scene(cfg: AblationBenchConfig, seed: int) -> Path:
    """Raw capture + processed scene for ``seed`` (reused when already there, if its motion matches)."""
    root = cfg.out / f"seed{seed}"
    scene = root / "scene"
    raw = root / "raw"
    motion = motion_of(cfg, seed)
    if (raw / "scene.json").exists():
        written = json.loads((raw / "scene.json").read_text())["config"]["motion"]
        if written != motion:
            raise ValueError(f"{raw}: scene of seed {seed} has motion {written!r}, this run asks for {motion!r} "
                             "(pass the --motions it was made with, or another --out)")
    if (scene / "transforms.json").exists():
        return scene
    if not (raw / "exposures.csv").exists():
        write_synthetic_scene(SynthConfig(output_dir=raw, seed=seed, width=cfg.width, height=cfg.height, n_frames=cfg.n_frames,
                                          motion=motion, overwrite=True))  # type: ignore[arg-type]
    config = ProcessConfig(output=scene, poses=cfg.poses)  # type: ignore[arg-type]
    config.inputs.exposures = raw / "exposures.csv"
    config.inputs.events = raw / "events.h5"
    process(config)
    return scene


#: Written next to a run's config.yml when its ns-train finished (wall seconds): the run is complete.
TRAIN_SECONDS_FILE = "train_seconds.txt"


def run_name(label: str) -> str:
    """Folder name (ns-train --timestamp) of variant ``label``."""
    return label.replace(" ", "_").replace("+", "plus").replace("(", "").replace(")", "").replace(",", "")


def run_config_path(scene: Path, label: str, method: str, runs: Path) -> Path:
    """config.yml of variant ``label`` trained on ``scene`` under ``runs`` (finished when
    TRAIN_SECONDS_FILE is next to it)."""
    return runs / scene.parent.name / method / run_name(label) / "config.yml"


def train(cfg: Any, scene: Path, label: str, method: str, ablation: Any, runs: Path) -> Tuple[Path, float]:
    """ns-train one variant; returns (config.yml, wall seconds). ``cfg`` needs ``device``,
    ``iters`` and ``extra_train_args`` (an AblationBenchConfig, or benchmarks/suite.py's config)."""
    name = run_name(label)
    config_path = run_config_path(scene, label, method, runs)
    timing = config_path.parent / TRAIN_SECONDS_FILE
    if config_path.exists() and timing.exists():
        return config_path, float(timing.read_text())
    cmd = [
        str(Path(sys.executable).parent / "ns-train"), method, "--data", str(scene),
        "--output-dir", str(runs), "--experiment-name", scene.parent.name, "--timestamp", name,
        "--machine.device-type", _device(cfg.device), "--steps-per-save", str(cfg.iters), "--vis", "tensorboard",
        *run_length_args(cfg.iters),
    ]
    if ablation is not None:
        cmd += ["--pipeline.model.ablation", ablation]
    cmd += shlex.split(cfg.extra_train_args)
    CONSOLE.log(f"[bench] {scene.parent.name} {label}: {' '.join(cmd[1:])}")
    start = time.time()
    log = config_path.parent.parent / f"{name}.log"
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "w") as handle:
        result = subprocess.run(cmd, stdout=handle, stderr=subprocess.STDOUT, env=dict(os.environ, PYTHONUNBUFFERED="1"))
    seconds = time.time() - start
    if result.returncode != 0:
        raise RuntimeError(f"ns-train failed for {label} on {scene} (see {log})")
    timing.write_text(f"{seconds:.1f}")
    return config_path, seconds


def evaluate_cached(config_path: Path, label: str) -> Dict[str, Any]:
    """edygs-eval's metrics of a run: read back when its eval/metrics.json is newer than every
    checkpoint (a re-run of the benchmark, or seeds run as separate processes, then merged)."""
    metrics_file = config_path.parent / "eval" / "metrics.json"
    checkpoints = list((config_path.parent / "nerfstudio_models").glob("*.ckpt"))
    if metrics_file.is_file() and checkpoints and metrics_file.stat().st_mtime > max(c.stat().st_mtime for c in checkpoints):
        metrics = json.loads(metrics_file.read_text())
        if label in metrics:
            return metrics
    return evaluate_run(config_path, config_path.parent / "eval", max_grids=2, method=label)


def _mean(entry: Any) -> Any:
    return entry.get("mean") if isinstance(entry, dict) else entry


def row_of(metrics: Dict[str, Any], label: str, seconds: float) -> Dict[str, Any]:
    """The numbers of run ``label`` (its rows in evaluate_run's metrics), flattened: ``input_*``,
    ``novel_*`` (novel poses fitted per view), ``novel_nofit_*`` (not fitted) and ``novel_anchor_*``
    (placed relative to the nearest training latent); None in metrics written before a split existed."""
    splits = metrics[label]
    row: Dict[str, Any] = {"train_seconds": seconds}
    for split, prefix in ((INPUT_SPLIT, "input"), (NOVEL_SPLIT, "novel"), (NOVEL_UNFITTED_SPLIT, "novel_nofit"),
                          (NOVEL_ANCHORED_SPLIT, "novel_anchor")):
        for key in ("psnr", "ssim", "lpips_alex", "mask_iou", "mask_mean", *REGION_PSNR_KEYS, *COVISIBILITY_KEYS):
            value = _mean(splits.get(split, {}).get(key))
            row[f"{prefix}_{key}"] = value if isinstance(value, (int, float)) else None
    for split, prefix in (("poses (initial)", "ate_initial"), ("poses (refined)", "ate_refined")):
        value = splits.get(split, {}).get("ate")
        row[prefix] = value if isinstance(value, (int, float)) else None
    return row


def _fmt(value: Any, digits: int) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def markdown(results: Dict[str, Any]) -> str:
    """Mean over seeds per variant."""
    lines = [
        "| Variant | in PSNR↑ | in SSIM↑ | in PSNR dyn↑ | in PSNR static↑ | novel PSNR↑ | novel SSIM↑ | LPIPS(alex)↓ | mask IoU↑ | ATE init | ATE refined | train s |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for label, rows in results["rows"].items():
        def mean(key: str) -> Any:
            values = [r[key] for r in rows if r.get(key) is not None]
            return sum(values) / len(values) if values else None

        lpips = mean("input_lpips_alex")
        lines.append(
            f"| {label} | {_fmt(mean('input_psnr'), 2)} | {_fmt(mean('input_ssim'), 4)} | {_fmt(mean('input_psnr_dynamic'), 2)} | "
            f"{_fmt(mean('input_psnr_static'), 2)} | {_fmt(mean('novel_psnr'), 2)} | "
            f"{_fmt(mean('novel_ssim'), 4)} | {'n/a (weights missing)' if lpips is None else f'{lpips:.4f}'} | "
            f"{_fmt(mean('input_mask_iou'), 3)} | {_fmt(mean('ate_initial'), 4)} | {_fmt(mean('ate_refined'), 4)} | {_fmt(mean('train_seconds'), 0)} |"
        )
    refs = results.get("references", {})
    for label, values in refs.items():
        lines.append(f"| {label} (image itself) | {_fmt(values.get('psnr'), 2)} | {_fmt(values.get('ssim'), 4)} | "
                     f"{_fmt(values.get('psnr_dynamic'), 2)} | {_fmt(values.get('psnr_static'), 2)} | | | | | | | |")
    seeds = sorted({(r["seed"], r.get("motion", "?")) for rows in results["rows"].values() for r in rows})
    if len(seeds) > 1:
        lines += ["", "Input-view PSNR per scene (mask IoU in brackets):", "",
                  "| Variant | " + " | ".join(f"seed {s} ({m})" for s, m in seeds) + " |",
                  "| --- |" + " --- |" * len(seeds)]
        for label, rows in results["rows"].items():
            by_seed = {r["seed"]: r for r in rows}
            cells = []
            for seed, _ in seeds:
                r = by_seed.get(seed)
                iou = "" if r is None or r.get("input_mask_iou") is None else f" ({r['input_mask_iou']:.2f})"
                cells.append("-" if r is None else _fmt(r.get("input_psnr"), 2) + iou)
            lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(cfg: AblationBenchConfig) -> Dict[str, Any]:
    cfg.out.mkdir(parents=True, exist_ok=True)
    runs = cfg.out / "runs"
    chosen = [v for v in VARIANTS if v[0] in cfg.variants]
    results: Dict[str, Any] = {
        "command": " ".join([Path(sys.argv[0]).name] + sys.argv[1:]),
        "machine": f"{platform.node()} {platform.processor() or platform.machine()}, {os.cpu_count()} cores, device {_device(cfg.device)}",
        "date": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "config": {k: str(v) for k, v in vars(cfg).items()},
        "rows": {label: [] for label, _, _ in chosen},
        "references": {},
    }
    ref_values: Dict[str, List[Dict[str, Any]]] = {}
    for seed in cfg.seeds:
        scene = make_scene(cfg, seed)
        for label, method, ablation in chosen:
            config_path, seconds = train(cfg, scene, label, method, ablation, runs)
            metrics = evaluate_cached(config_path, label)
            row = row_of(metrics, label, seconds)
            row["seed"] = seed
            row["motion"] = motion_of(cfg, seed)
            results["rows"][label].append(row)
            for ref_label in ("EDI latent", "blurry input"):
                ref = metrics.get(ref_label, {}).get(INPUT_SPLIT)
                if ref and method == "edygs" and ablation == "full":
                    ref_values.setdefault(ref_label, []).append({k: _mean(ref.get(k)) for k in REFERENCE_KEYS})
            (cfg.out / "results.json").write_text(json.dumps(results, indent=2))
    for ref_label, entries in ref_values.items():
        results["references"][ref_label] = {
            k: sum(e[k] for e in entries) / len(entries) if all(isinstance(e[k], (int, float)) for e in entries) else None
            for k in REFERENCE_KEYS
        }
    table = markdown(results)
    (cfg.out / "results.json").write_text(json.dumps(results, indent=2))
    (cfg.out / "results.md").write_text(
        f"Command: `{results['command']}`  \nMachine: {results['machine']}  \nDate: {results['date']}\n\n{table}\n"
    )
    CONSOLE.print(table)
    return results


if __name__ == "__main__":
    main(tyro.cli(AblationBenchConfig))
