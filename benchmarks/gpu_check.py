"""Issue 19's one prepared GPU check: everything a session with a lent GPU runs, in one command.

Stages (each timed; results rewritten after every stage, so a run cut short keeps what it did):

1. ``doctor``: ``edygs-doctor``'s report and diagnosis (torch, CUDA, toolkit, GPU arch, gsplat).
2. ``parity``: the CUDA parity tests (``tests/test_rasterizer_parity_cuda.py``: torch rasteriser
   against gsplat, and the torch rasteriser on CUDA tensors) in a pytest subprocess.
3. ``train``: a short ``ns-train edygs`` on the device, shaped (``configs/run_length.py``) so it
   crosses the static -> dynamic switch, an opacity reset and pruning after it; probes record
   the switch step, the reset steps, every refinement's counts and the step time.
4. ``render``: ``ns-render camera-path`` of the run (a few instants along a training camera).
5. ``eval``: ``edygs-eval`` of the run.
6. ``bench``: the 400x400 x 60-frame scene (simulated and processed in a child process started
   before the first stage), EDyGS and then the blurry baseline at the GPU defaults
   (the method's own MLP and thresholds; the run length scaled by ``run_length_args``): training
   seconds, seconds per step, PSNR / SSIM / mask IoU from ``edygs-eval``'s ``evaluate_run``.

``ns-train``, ``ns-render`` and ``edygs-eval`` run in this process (their own config classes,
parsed from the same arguments the CLIs take; the JSON records each as a command line): a
nerfstudio import costs 25 s on the 2-core CPU machine, which the dry mode cannot afford thrice.

Writes ``OUT/gpu_check.json`` and ``OUT/gpu_check.md``. ``--device cpu`` is the dry mode: tiny
sizes and few iterations (every default below has a CPU value), the CUDA-only parity tests skip,
everything else runs end to end (tests/test_gpu_check.py runs it).

Usage::

    bash scripts/gpu_check.sh --out gpu_check            # on a machine with a GPU (about 10 min)
    bash scripts/gpu_check.sh --device cpu --out /tmp/gc # dry mode, about a minute
"""

from __future__ import annotations

import json
import os
import platform
import shlex
import shutil
import subprocess
import sys
import time
import traceback
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable, Dict, List, Literal, Optional

import tyro

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(Path(__file__).resolve().parent))

STAGES = ("doctor", "parity", "train", "render", "eval", "bench")
#: (cuda, cpu) defaults of the sized options
SIZES: Dict[str, tuple] = {
    "train_iters": (1500, 40),
    "train_scene": ((128, 96, 12), (48, 36, 4)),
    "bench_iters": (3000, 20),
    "bench_scene": ((400, 400, 60), (48, 36, 4)),
    "eval_fit_steps": (40, 0),
}
#: tiny simulation settings of the dry mode (tests/train_helpers.TINY_SCENE; its scenes also start
#: from 2000 random points, not 20k)
TINY_SIM = dict(k=5, sim_steps_per_exposure=12)
#: the CPU demo's deformation MLP (scripts/demo.sh): every CPU run gets it
CPU_MLP = ["--pipeline.model.deformation.width", "64", "--pipeline.model.deformation.depth", "4",
           "--pipeline.model.deformation.skip-layer", "2"]
#: dry mode only: a few rigid-tracking steps (the plumbing, not the fit; a barely trained tiny
#: model finds several spurious regions, and 25 steps each took 30 s of the dry run)
DRY_ARGS = ["--pipeline.model.rigid-track.steps", "3"]
#: bench rows: (label, ns-train method, ablation preset)
BENCH_VARIANTS = (("EDyGS", "edygs", "full"), ("blurry D3DGS", "edygs-blurry", None))


@dataclass
class GpuCheckConfig:
    """Run issue 19's GPU check (or its CPU dry mode) and write OUT/gpu_check.{json,md}."""

    out: Path = Path("gpu_check")
    """output folder (scenes, runs, renders, gpu_check.json, gpu_check.md)"""
    device: Literal["cuda", "cpu"] = "cuda"
    """cuda: the real check; cpu: the dry mode (tiny sizes, few iterations)"""
    stages: List[str] = field(default_factory=lambda: list(STAGES))
    """stages to run, of: doctor parity train render eval bench"""
    rasterizer: Literal["auto", "torch", "gsplat"] = "auto"
    """--pipeline.model.rasterizer of every run (auto: gsplat on CUDA)"""
    train_iters: Optional[int] = None
    """iterations of the short run (default 1500 on CUDA, 40 on CPU)"""
    bench_iters: Optional[int] = None
    """iterations of each benchmark run (default 3000 on CUDA, 20 on CPU)"""
    bench_size: Optional[List[int]] = None
    """benchmark scene WIDTH HEIGHT FRAMES (default 400 400 60 on CUDA, 48 36 4 on CPU)"""
    eval_fit_steps: Optional[int] = None
    """edygs-eval's novel-view pose-fit steps (default 40 on CUDA, 0 on CPU)"""
    bench_variants: List[str] = field(default_factory=lambda: [label for label, _, _ in BENCH_VARIANTS])
    """benchmark runs, of: EDyGS, blurry D3DGS"""
    bench_parallel: bool = False
    """train the benchmark runs side by side, each in its own process (a host-bound GPU run leaves
    the GPU and the other cores idle)"""
    deadline_s: float = 570.0
    """a stage (or bench run) that would start after this many seconds is skipped, not started"""
    extra_train_args: str = ""
    """more ns-train arguments for every run, one quoted string"""
    results: Optional[Path] = None
    """also copy gpu_check.json/.md here after every stage (a folder that survives a cut-short run)"""

    def size(self, key: str) -> Any:
        value = getattr(self, key, None) if key != "bench_scene" else self.bench_size
        if value is not None:
            return tuple(value) if isinstance(value, list) else value
        return SIZES[key][0 if self.device == "cuda" else 1]


class Check:
    """The results so far, written to OUT after every stage."""

    def __init__(self, cfg: GpuCheckConfig) -> None:
        self.cfg, self.start = cfg, time.time()
        cfg.out.mkdir(parents=True, exist_ok=True)
        self.data: Dict[str, Any] = {
            "command": " ".join(["gpu_check"] + [shlex.quote(a) for a in sys.argv[1:]]),
            "date": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
            "machine": f"{platform.node()} {platform.machine()}, {os.cpu_count()} cores",
            "device": cfg.device, "dry_run": cfg.device == "cpu",
            "config": {k: str(v) for k, v in vars(cfg).items()},
            "stages": {},
        }

    def elapsed(self) -> float:
        return time.time() - self.start

    def run(self, name: str, fn: Callable[[], Dict[str, Any]]) -> Optional[Dict[str, Any]]:
        if name not in self.cfg.stages:
            return None
        if self.elapsed() > self.cfg.deadline_s:
            self.data["stages"][name] = {"status": "skipped", "reason": f"deadline {self.cfg.deadline_s:.0f} s passed"}
            self.write()
            return None
        print(f"[gpu_check] {name} ...", flush=True)
        t0 = time.time()
        try:
            result = {"status": "ok", **fn()}
        except (Exception, SystemExit) as exc:  # noqa: BLE001 - a failed stage is a result; the next ones still run
            result = {"status": "failed", "error": f"{type(exc).__name__}: {exc}".splitlines()[0][:500],
                      "traceback": traceback.format_exc()[-3000:]}
        result["seconds"] = round(time.time() - t0, 1)
        self.data["stages"][name] = result
        print(f"[gpu_check] {name}: {result['status']} in {result['seconds']} s", flush=True)
        self.write()
        return result

    def write(self) -> None:
        self.data["total_seconds"] = round(self.elapsed(), 1)
        self.data["ok"] = all(s.get("status") in ("ok", "skipped") for s in self.data["stages"].values())
        (self.cfg.out / "gpu_check.json").write_text(json.dumps(self.data, indent=2, default=str) + "\n")
        (self.cfg.out / "gpu_check.md").write_text(markdown(self.data))
        if self.cfg.results is not None:
            self.cfg.results.mkdir(parents=True, exist_ok=True)
            for name in ("gpu_check.json", "gpu_check.md"):
                shutil.copyfile(self.cfg.out / name, self.cfg.results / name)


# ----------------------------------------------------------------------------- stages


def stage_doctor() -> Dict[str, Any]:
    from edygs_ns import cuda_setup

    report = cuda_setup.collect_report()
    verdicts = cuda_setup.diagnose(report)
    print(cuda_setup.format_report(report, verdicts), flush=True)
    return {**cuda_setup.report_dict(report, verdicts), "text": cuda_setup.format_report(report, verdicts)}


def stage_parity(cfg: GpuCheckConfig) -> Dict[str, Any]:
    xml = cfg.out / "parity.xml"
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", f"--junitxml={xml}",
           str(REPO / "tests" / "test_rasterizer_parity_cuda.py")]
    run = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=max(60.0, cfg.deadline_s))
    suite = ET.parse(xml).getroot()
    suite = suite if suite.tag == "testsuite" else suite.find("testsuite")
    counts = {k: int(suite.get(k, 0)) for k in ("tests", "failures", "errors", "skipped")}
    counts["passed"] = counts["tests"] - counts["failures"] - counts["errors"] - counts["skipped"]
    if run.returncode not in (0, 5) or counts["failures"] or counts["errors"]:
        raise RuntimeError(f"parity tests failed: {counts}; {run.stdout.strip().splitlines()[-1] if run.stdout.strip() else ''}")
    return {"command": " ".join(cmd[2:]), **counts, "summary": run.stdout.strip().splitlines()[-1] if run.stdout.strip() else ""}


def make_scene(root: Path, size: Optional[tuple], dry: bool, seed: int = 0, workers: int = 0) -> Path:
    """edygs-synth + edygs-process (true poses) into root/{raw,scene}, in this process; reused when
    there. ``size``: (width, height, frames), None for edygs-synth's defaults (the demo scene);
    ``workers``: the simulator's render processes (0: one per core; the dry mode: 1)."""
    from edygs_ns.scripts.process import ProcessConfig, process
    from edygs_ns.scripts.synth import SynthConfig, write_synthetic_scene

    root = Path(root)
    scene = root / "scene"
    if (scene / "transforms.json").exists():
        return scene
    extra = dict(TINY_SIM) if dry else {}
    if size is not None:
        extra.update(width=size[0], height=size[1], n_frames=size[2])
    raw = write_synthetic_scene(SynthConfig(output_dir=root / "raw", seed=seed, overwrite=True, workers=1 if dry else workers, **extra))
    config = ProcessConfig(output=scene, poses="given", overwrite=True, **({"num_random_points": 2000} if dry else {}))
    config.inputs.exposures = raw / "exposures.csv"
    config.inputs.events = raw / "events.h5"
    process(config)
    return scene


def start_scene(cfg: GpuCheckConfig, name: str, size: tuple) -> Optional[subprocess.Popen]:
    """make_scene in a child process, so the benchmark scene is simulated and processed while the
    earlier stages use the GPU; None when it is already there. Its log: OUT/NAME.log."""
    root = cfg.out / name
    if (root / "scene" / "transforms.json").exists():
        return None
    workers = max(1, (os.cpu_count() or 2) - 2)  # leave two cores to the stages running meanwhile
    call = f"import gpu_check as g; g.make_scene({str(root)!r}, {tuple(size)!r}, {cfg.device == 'cpu'!r}, workers={workers})"
    log = open(cfg.out / f"{name}.log", "w")
    return subprocess.Popen([sys.executable, "-c", call], cwd=Path(__file__).resolve().parent, stdout=log, stderr=subprocess.STDOUT)


def wait_scene(cfg: GpuCheckConfig, name: str, child: Optional[subprocess.Popen]) -> None:
    """Wait for start_scene's child; a failure raises with the end of its log."""
    if child is None:
        return
    if child.wait() != 0:
        tail = (cfg.out / f"{name}.log").read_text(errors="replace").strip().splitlines()[-3:]
        raise RuntimeError(f"making {cfg.out / name} failed (exit {child.returncode}): {' / '.join(tail)}")


def train_args(cfg: GpuCheckConfig, method: str, scene: Path, runs: Path, name: str, iters: int,
               extra: Optional[List[str]] = None) -> List[str]:
    """``ns-train`` arguments of one run (after the program name)."""
    from edygs_ns.configs.run_length import run_length_args

    args = [method, "--data", str(scene), "--output-dir", str(runs), "--experiment-name", "check", "--timestamp", name,
            "--machine.device-type", cfg.device, "--vis", "tensorboard", "--steps-per-save", str(iters),
            "--pipeline.model.rasterizer", cfg.rasterizer, *run_length_args(iters)]
    if cfg.device == "cpu":
        args += CPU_MLP + DRY_ARGS
    return args + (extra or []) + shlex.split(cfg.extra_train_args)


def short_run_shape(iters: int) -> List[str]:
    """Densification of the short run: refine ~25 times, one opacity reset at half the run (after
    the static -> dynamic switch at 40 %), refinements (pruning large Gaussians) after it."""
    every = max(iters // 25, 2)
    reset = max(every, (iters // 2) // every * every)
    return ["--pipeline.model.densify.refine-every", str(every), "--pipeline.model.densify.reset-every", str(reset),
            "--pipeline.model.densify.verbose", "True"]


def ns_train(args: List[str], probe: Optional[Dict[str, Any]] = None) -> Path:
    """``ns-train ARGS`` in this process (nerfstudio's train_loop); returns the run's config.yml.
    ``probe``: filled with the phase switch, opacity resets and refinements as they happen."""
    import torch
    from nerfstudio.configs.method_configs import AnnotatedBaseConfigUnion

    from edygs_ns.compat import allow_nerfstudio_checkpoints

    allow_nerfstudio_checkpoints()
    from nerfstudio.scripts.train import _set_random_seed

    config = tyro.cli(AnnotatedBaseConfigUnion, args=args)
    if config.data:  # what nerfstudio's train.main does before launch()
        config.pipeline.datamanager.data = config.data
    config.set_timestamp()
    config.save_config()
    _set_random_seed(config.machine.seed)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    if probe is not None:
        attach_probe(trainer.pipeline.model, probe)
    if torch.cuda.is_available():
        torch.cuda.reset_peak_memory_stats()
    t0 = time.time()
    trainer.train()
    if probe is not None:
        if torch.cuda.is_available():
            torch.cuda.synchronize()
            probe["peak_gpu_memory_gib"] = round(torch.cuda.max_memory_allocated() / 2**30, 2)
        probe["train_seconds"] = round(time.time() - t0, 2)
        probe["seconds_per_step"] = round(probe["train_seconds"] / max(config.max_num_iterations, 1), 4)
        probe["gaussians_final"] = int(len(trainer.pipeline.model.gauss_params["means"]))
    return config.get_base_dir() / "config.yml"


def attach_probe(model: Any, probe: Dict[str, Any]) -> None:
    """Wrap the model's densification step to record the phase switch, opacity resets and
    refinements (counts from the strategy state)."""
    import torch

    strategy = model.strategy
    inner = strategy.step_post_backward
    probe.update(switch_step=None, reset_steps=[], refinements=[])
    prune_opa = strategy.prune_opa

    def wrapped(params, optimizers, state, step, info, packed=False):
        if probe["switch_step"] is None and str(getattr(model.phase, "name", model.phase)).upper().endswith("DYNAMIC"):
            probe["switch_step"] = int(step)
        before = float(torch.sigmoid(params["opacities"].detach()).max()) if len(params["opacities"]) else 0.0
        last = state.get("last_refine")
        result = inner(params=params, optimizers=optimizers, state=state, step=step, info=info, packed=packed)
        after = float(torch.sigmoid(params["opacities"].detach()).max()) if len(params["opacities"]) else 0.0
        if step > 0 and before > 2 * prune_opa * 1.01 and after <= 2 * prune_opa * 1.01:
            probe["reset_steps"].append(int(step))
        record = state.get("last_refine")
        if record is not None and record is not last and record.get("step") == step:
            probe["refinements"].append({**record, "gaussians": int(len(params["means"]))})
        return result

    strategy.step_post_backward = wrapped


def stage_train(cfg: GpuCheckConfig) -> Dict[str, Any]:
    iters = cfg.size("train_iters")
    scene = make_scene(cfg.out / "train_scene", cfg.size("train_scene"), cfg.device == "cpu")
    args = train_args(cfg, "edygs", scene, cfg.out / "runs", "short", iters, short_run_shape(iters))
    probe: Dict[str, Any] = {}
    config = ns_train(args, probe)
    reset = probe["reset_steps"][0] if probe["reset_steps"] else None
    after = [r for r in probe["refinements"] if reset is not None and r["step"] > reset]
    checks = {
        "crossed static->dynamic switch": probe["switch_step"] is not None,
        "opacity reset after the switch": reset is not None and probe["switch_step"] is not None and reset > probe["switch_step"],
        "pruning after the reset": bool(after),
    }
    result = {"command": "ns-train " + " ".join(shlex.quote(a) for a in args), "config": str(config), "iters": iters,
              **probe, "pruned_total": sum(r.get("pruned", 0) for r in probe["refinements"]),
              "pruned_after_reset": sum(r.get("pruned", 0) for r in after), "checks": checks}
    if not all(checks.values()):
        raise RuntimeError(f"short run missed: {[k for k, v in checks.items() if not v]} ({json.dumps(result, default=str)[:400]})")
    return result


def stage_render(cfg: GpuCheckConfig, config: Path) -> Dict[str, Any]:
    from nerfstudio.scripts.render import RenderCameraPath

    scene = Path(json.loads((cfg.out / "gpu_check.json").read_text())["stages"]["train"]["command"].split("--data ")[1].split()[0])
    cams = json.loads((scene / "transforms.json").read_text())
    frame = cams["frames"][0]
    width, height = int(cams.get("w", frame.get("w", 48))), int(cams.get("h", frame.get("h", 36)))
    fov = 50.0
    times = [0.0, 1.0 / 3, 2.0 / 3, 1.0]
    path = cfg.out / "camera_path.json"
    path.write_text(json.dumps({"render_height": height, "render_width": width, "seconds": len(times), "fps": 1,
                                "camera_path": [{"camera_to_world": sum(frame["transform_matrix"], []), "fov": fov,
                                                 "aspect": width / height, "render_time": t} for t in times]}))
    out = cfg.out / "render"
    names = ["rgb", "mask", "rgb_static", "depth"]
    from nerfstudio.utils import install_checks

    t0 = time.time()
    check_ffmpeg = install_checks.check_ffmpeg_installed
    if shutil.which("ffmpeg") is None:  # images need no ffmpeg, but ns-render exits without it
        install_checks.check_ffmpeg_installed = lambda: None
    try:
        RenderCameraPath(load_config=config, camera_path_filename=path, output_path=out, output_format="images",
                         rendered_output_names=names).main()
    finally:
        install_checks.check_ffmpeg_installed = check_ffmpeg
    seconds = time.time() - t0
    frames = sorted(p.name for p in out.glob("*") if p.is_file())
    if len(frames) != len(times):
        raise RuntimeError(f"ns-render wrote {len(frames)} images, expected {len(times)}")
    return {"command": f"ns-render camera-path --load-config {config} --camera-path-filename {path} --output-path {out} "
                       f"--output-format images --rendered-output-names {' '.join(names)}",
            "frames": len(frames), "size": [width, height], "seconds_per_frame": round(seconds / len(times), 3)}


def _metric_row(metrics: Dict[str, Any], label: str) -> Dict[str, Any]:
    from ablations import row_of

    row = row_of(metrics, label, 0.0)
    row.pop("train_seconds", None)
    return {k: v for k, v in row.items() if v is not None}


def stage_eval(cfg: GpuCheckConfig, config: Path) -> Dict[str, Any]:
    from edygs_ns.eval.novel_pose_fit import NovelPoseFitConfig
    from edygs_ns.scripts.eval import EvalCommand

    steps = cfg.size("eval_fit_steps")
    out = config.parent / "eval"
    metrics = EvalCommand(load_config=config, output=out, max_grids=1, method="EDyGS",
                          novel_pose_fit=NovelPoseFitConfig(steps=steps)).main()
    return {"command": f"edygs-eval --load-config {config} --output {out} --max-grids 1 --method EDyGS --novel-pose-fit.steps {steps}",
            "metrics_json": str(out / "metrics.json"), **_metric_row(metrics, "EDyGS")}


def stage_bench(cfg: GpuCheckConfig, check: Check, child: Optional[subprocess.Popen]) -> Dict[str, Any]:
    """``child``: start_scene's process making the scene (None: made here, or already there)."""
    from edygs_ns.eval.evaluate import evaluate_run
    from edygs_ns.eval.novel_pose_fit import NovelPoseFitConfig

    size, iters = cfg.size("bench_scene"), cfg.size("bench_iters")
    t0 = time.time()
    wait_scene(cfg, "bench_scene", child)
    scene = make_scene(cfg.out / "bench_scene", size, cfg.device == "cpu")
    rows: Dict[str, Any] = {"scene": {"width": size[0], "height": size[1], "frames": size[2], "waited_seconds": round(time.time() - t0, 1)},
                            "iters": iters, "runs": {}}
    variants = [v for v in BENCH_VARIANTS if v[0] in cfg.bench_variants]
    if cfg.bench_parallel and len(variants) > 1:
        rows["runs"] = bench_side_by_side(cfg, check, [label for label, _, _ in variants])
        failed = [label for label, run in rows["runs"].items() if run.get("status") == "failed"]
        if failed:
            rows.update(status="failed", error="; ".join(f"{label}: {rows['runs'][label]['reason']}" for label in failed))
        return rows
    for label, method, ablation in variants:
        if check.elapsed() > cfg.deadline_s:
            rows["runs"][label] = {"status": "skipped", "reason": "deadline"}
            continue
        extra = ["--pipeline.model.ablation", ablation] if ablation else []
        args = train_args(cfg, method, scene, cfg.out / "bench_runs", _slug(label), iters, extra)
        probe: Dict[str, Any] = {}
        config = ns_train(args, probe)
        metrics = evaluate_run(config, config.parent / "eval", max_grids=1, method=label,
                               novel_pose_fit=NovelPoseFitConfig(steps=cfg.size("eval_fit_steps")))
        rows["runs"][label] = {"command": "ns-train " + " ".join(shlex.quote(a) for a in args),
                               "train_seconds": probe["train_seconds"], "seconds_per_step": probe["seconds_per_step"],
                               "gaussians_final": probe["gaussians_final"], "peak_gpu_memory_gib": probe.get("peak_gpu_memory_gib"),
                               **_metric_row(metrics, label)}
        check.data["stages"]["bench"] = {"status": "running", **rows}
        check.write()
    return rows


def _slug(label: str) -> str:
    """A bench row's label as a file name part ("blurry D3DGS" -> "blurry_D3DGS")."""
    return label.replace(" ", "_")


def bench_side_by_side(cfg: GpuCheckConfig, check: Check, labels: List[str]) -> Dict[str, Any]:
    """Each benchmark run in a child ``gpu_check --stages bench --bench-variants LABEL`` of its own
    (OUT/bench_LABEL, the scene linked in), all at once; their rows, merged. Logs: OUT/bench_LABEL.log."""
    children = []
    for label in labels:
        sub = cfg.out / f"bench_{_slug(label)}"
        sub.mkdir(parents=True, exist_ok=True)
        if not (sub / "bench_scene").exists():
            (sub / "bench_scene").symlink_to((cfg.out / "bench_scene").resolve(), target_is_directory=True)
        cmd = [sys.executable, str(Path(__file__).resolve()), "--out", str(sub), "--device", cfg.device,
               "--stages", "bench", "--bench-variants", label, "--bench-iters", str(cfg.size("bench_iters")),
               "--bench-size", *map(str, cfg.size("bench_scene")), "--eval-fit-steps", str(cfg.size("eval_fit_steps")),
               "--rasterizer", cfg.rasterizer, f"--extra-train-args={cfg.extra_train_args}",
               "--deadline-s", str(max(0.0, cfg.deadline_s - check.elapsed()))]
        if cfg.results is not None:
            cmd += ["--results", str(cfg.results / sub.name)]
        log = open(cfg.out / f"{sub.name}.log", "w")
        children.append((label, sub, log, subprocess.Popen(cmd, cwd=REPO, stdout=log, stderr=subprocess.STDOUT)))
    runs: Dict[str, Any] = {}
    for label, sub, log, child in children:
        child.wait()
        log.close()
        try:
            stage = json.loads((sub / "gpu_check.json").read_text())["stages"]["bench"]
            runs[label] = stage["runs"][label] if stage["status"] == "ok" else {"status": "failed", "reason": stage["error"]}
        except (OSError, KeyError, ValueError) as err:
            runs[label] = {"status": "failed", "reason": f"child exit {child.returncode}, no row ({err!r}); see {sub}.log"}
    return runs


# ----------------------------------------------------------------------------- report


def _fmt(v: Any, digits: int = 2) -> str:
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return f"{v:.{digits}f}"
    return "-" if v is None else str(v)


def markdown(data: Dict[str, Any]) -> str:
    """gpu_check.md: the summary a README section can quote."""
    s = data["stages"]
    lines = [f"# GPU check ({'dry mode, CPU' if data['dry_run'] else data['device']})", "",
             f"Command: `{data['command']}`  ", f"Machine: {data['machine']}  ", f"Date: {data['date']}  ",
             f"Total: {_fmt(data.get('total_seconds'), 1)} s; all stages ok: {_fmt(data.get('ok'))}", "",
             "| stage | status | seconds | notes |", "| --- | --- | --- | --- |"]
    for name in STAGES:
        st = s.get(name)
        if st is None:
            continue
        note = st.get("error") or st.get("reason") or ""
        if name == "doctor" and st.get("diagnosis"):
            note = st["diagnosis"][0]["line"]
        elif name == "parity" and "tests" in st:
            note = f"{st['passed']} passed, {st['skipped']} skipped, {st['failures']} failed (of {st['tests']})"
        elif name == "train" and "checks" in st:
            note = (f"{st['iters']} it, {_fmt(st.get('seconds_per_step'), 4)} s/step; switch at {st.get('switch_step')}, "
                    f"reset at {st.get('reset_steps')}, {st.get('pruned_after_reset')} pruned after it")
        elif name == "render" and "frames" in st:
            note = f"{st['frames']} frames {st['size'][0]}x{st['size'][1]}, {st['seconds_per_frame']} s/frame"
        elif name == "eval" and "input_psnr" in st:
            note = f"input PSNR {_fmt(st.get('input_psnr'))} dB, novel {_fmt(st.get('novel_psnr'))} dB"
        lines.append(f"| {name} | {st.get('status')} | {_fmt(st.get('seconds'), 1)} | {str(note).replace('|', '/')} |")
    bench = s.get("bench", {})
    if bench.get("runs"):
        sc = bench["scene"]
        lines += ["", f"## Benchmark: {sc['width']}x{sc['height']}, {sc['frames']} frames, {bench['iters']} iterations", "",
                  "| run | train s | s/step | Gaussians | input PSNR | input SSIM | novel PSNR | novel PSNR (no fit) | mask IoU |",
                  "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
        for label, r in bench["runs"].items():
            if r.get("status") in ("skipped", "failed"):
                lines.append(f"| {label} | {r['status']} ({r.get('reason')}) | | | | | | | |")
                continue
            lines.append(f"| {label} | {_fmt(r.get('train_seconds'), 1)} | {_fmt(r.get('seconds_per_step'), 4)} | "
                         f"{_fmt(r.get('gaussians_final'))} | {_fmt(r.get('input_psnr'))} | {_fmt(r.get('input_ssim'), 3)} | "
                         f"{_fmt(r.get('novel_psnr'))} | {_fmt(r.get('novel_nofit_psnr'))} | {_fmt(r.get('input_mask_iou'), 3)} |")
    if s.get("doctor", {}).get("text"):
        lines += ["", "## edygs-doctor", "", "```", s["doctor"]["text"], "```"]
    return "\n".join(lines) + "\n"


def main(cfg: GpuCheckConfig) -> Dict[str, Any]:
    unknown = [s for s in cfg.stages if s not in STAGES]
    if unknown:
        raise SystemExit(f"gpu_check: unknown stages {unknown}; choose from {' '.join(STAGES)}")
    if cfg.device == "cuda":
        import torch

        if not torch.cuda.is_available():
            raise SystemExit("gpu_check: no CUDA device here; pass --device cpu for the dry mode")
    check = Check(cfg)
    scene_child = start_scene(cfg, "bench_scene", cfg.size("bench_scene")) if "bench" in cfg.stages else None
    check.run("doctor", stage_doctor)
    check.run("parity", lambda: stage_parity(cfg))
    train = check.run("train", lambda: stage_train(cfg))
    config = Path(train["config"]) if train and train.get("status") == "ok" else None
    if config is not None:
        check.run("render", lambda: stage_render(cfg, config))
        check.run("eval", lambda: stage_eval(cfg, config))
    else:
        for name in ("render", "eval"):
            if name in cfg.stages:
                check.data["stages"][name] = {"status": "skipped", "reason": "no trained run (train stage failed or not run)"}
    check.run("bench", lambda: stage_bench(cfg, check, scene_child))
    if scene_child is not None and scene_child.poll() is None:  # bench skipped: do not leave it running
        scene_child.kill()
    check.write()
    print(f"[gpu_check] wrote {cfg.out / 'gpu_check.json'} and {cfg.out / 'gpu_check.md'}; all ok: {check.data['ok']}", flush=True)
    return check.data


if __name__ == "__main__":
    result = main(tyro.cli(GpuCheckConfig))
    sys.exit(0 if result["ok"] else 1)
