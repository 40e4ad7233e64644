"""Measure edygs-process on a synthetic capture: registration, pose accuracy, time per step.

Writes the built-in synthetic scene (``edygs-synth`` defaults unless told otherwise, or reuses
``--raw``), runs ``edygs-process`` with COLMAP on it and prints:

- the share of latents COLMAP registered (target: all of them);
- the ATE of the COLMAP camera centres against the ground-truth poses after a Sim(3) (Umeyama)
  alignment, in world units and as a fraction of the scene extent (scene.json's room diagonal)
  and of the camera path's diameter;
- the wall time of each step (read, edi, poses, write) and in total.

Usage::

    python benchmarks/process_timing.py --work /tmp/process_bench
    python benchmarks/process_timing.py --work /tmp/bench400 --synth.width 400 --synth.height 400 --synth.n-frames 60
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Dict, Optional

import numpy as np
import tyro
from nerfstudio.utils.rich_utils import CONSOLE
from rich.table import Table

from edygs_ns.eval.trajectory import ate_rmse
from edygs_ns.events.edi import EdiConfig
from edygs_ns.preprocess.colmap import ColmapConfig
from edygs_ns.preprocess.inputs import InputConfig
from edygs_ns.preprocess.pipeline import ProcessConfig, process
from edygs_ns.sim.writer import SynthConfig, write_synthetic_scene


@dataclass
class BenchConfig:
    """Time edygs-process on a synthetic capture and check its COLMAP poses against ground truth."""

    work: Path = Path("/tmp/edygs_process_bench")
    """Scratch folder: raw/ (unless --raw) and scene/ are written here."""
    raw: Optional[Path] = None
    """An existing raw capture (edygs-synth output) to process instead of writing one."""
    synth: SynthConfig = field(default_factory=SynthConfig)
    """Synthetic scene written when --raw is not given (its output_dir is ignored)."""
    colmap: ColmapConfig = field(default_factory=ColmapConfig)
    """COLMAP settings of the run."""
    json_out: Optional[Path] = None
    """Also write the measurements to this JSON file."""


def _gt_c2w(raw: Path, frames: list) -> np.ndarray:
    """Ground-truth poses [N, 4, 4] matched to the processed frames by (blurry, latent) index."""
    gt = json.loads((raw / "gt" / "transforms.json").read_text())
    table = {(f["blurry_index"], f["latent_index"]): f["transform_matrix"] for f in gt["frames"]}
    return np.array([table[(f["blurry_index"], f["latent_index"])] for f in frames], dtype=np.float64)


def measure(config: BenchConfig) -> Dict[str, Any]:
    """Write (or reuse) the capture, process it, return the measurements."""
    config.work.mkdir(parents=True, exist_ok=True)
    raw = config.raw
    synth_seconds = None
    if raw is None:
        raw = config.work / "raw"
        start = time.perf_counter()
        write_synthetic_scene(replace(config.synth, output_dir=raw, overwrite=True))
        synth_seconds = time.perf_counter() - start
    scene = config.work / "scene"
    k = int(json.loads((raw / "gt" / "transforms.json").read_text()).get("k", EdiConfig().k))
    report = process(ProcessConfig(
        output=scene,
        inputs=InputConfig(exposures=raw / "exposures.csv", events=raw / "events.h5"),
        edi=EdiConfig(k=k),
        colmap=config.colmap,
        overwrite=True,
    ))
    frames = json.loads((scene / "transforms.json").read_text())["frames"]
    est = np.array([f["transform_matrix"] for f in frames], dtype=np.float64)
    gt = _gt_c2w(raw, frames)
    registered = np.ones(len(frames), dtype=bool)
    names = {f"{f['blurry_index']:04d}_{f['latent_index']}.png": i for i, f in enumerate(frames)}
    for name in report["unregistered_latents"]:
        registered[names[name]] = False
    ate = ate_rmse(est[registered], gt[registered])
    extent = json.loads((raw / "scene.json").read_text())
    h, w = np.load(scene / "event_maps.npy", mmap_mode="r").shape[-2:]
    return {
        "capture": str(raw),
        "frames": report["n_blurry"],
        "size": f"{w}x{h}",
        "k": k,
        "registered_latents": report["registered_latents"],
        "total_latents": report["total_latents"],
        "registered_share": report["registered_fraction"],
        "mean_reprojection_error_px": report["mean_reprojection_error_px"],
        "num_points": report["num_points"],
        "ate": ate,
        "ate_over_scene_extent": ate / extent["room_diameter"],
        "ate_over_camera_path": ate / extent["camera_path_diameter"],
        "step_seconds": report["step_seconds"],
        "process_seconds": sum(report["step_seconds"].values()),
        "synth_seconds": synth_seconds,
    }


def print_table(result: Dict[str, Any]) -> None:
    table = Table(title=f"edygs-process on {result['frames']} frames {result['size']}, k={result['k']}")
    table.add_column("measure")
    table.add_column("value", justify="right")
    table.add_row("latents registered", f"{result['registered_latents']}/{result['total_latents']} "
                                        f"({100 * result['registered_share']:.1f}%)")
    error = result["mean_reprojection_error_px"]
    table.add_row("mean reprojection error", "n/a" if error is None else f"{error:.3f} px")
    table.add_row("sparse points", f"{result['num_points']:,}")
    table.add_row("ATE (Sim(3)-aligned centres)", f"{result['ate']:.4f} units")
    table.add_row("ATE / scene extent (room diagonal)", f"{100 * result['ate_over_scene_extent']:.3f}%")
    table.add_row("ATE / camera path diameter", f"{100 * result['ate_over_camera_path']:.2f}%")
    for name, seconds in result["step_seconds"].items():
        table.add_row(f"time: {name}", f"{seconds:.1f} s")
    table.add_row("time: total", f"{result['process_seconds']:.1f} s")
    if result["synth_seconds"] is not None:
        table.add_row("(writing the synthetic capture)", f"{result['synth_seconds']:.1f} s")
    CONSOLE.print(table)


def main(config: BenchConfig) -> Dict[str, Any]:
    result = measure(config)
    print_table(result)
    if config.json_out is not None:
        config.json_out.write_text(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    main(tyro.cli(BenchConfig))
