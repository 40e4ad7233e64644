"""Rasteriser timings: forward and forward+backward of every backend, side by side.

Usage: ``python benchmarks/rasterizer.py --out FILE.json [--repeats 5] [--cases 20000x128 ...]
[--threads 1 2] [--backends torch cpu]``

Backends: ``torch`` (the reference), ``cpu`` (the compiled one, when it builds) and ``gsplat``
(with CUDA). Every case runs each backend at each thread count in turn, so the ratios
(torch time / backend time, same case and threads) compare runs made minutes apart at most.

Scenes: one pinhole camera (53 degree field of view) looking at Gaussians spread uniformly over
its frustum between depths 2 and 6, random orientations, anisotropic log-normal scales, opacities
sigmoid(N(0, 1.5)). The world scale shrinks as 1/sqrt(N) so the depth complexity stays about
``--complexity`` Gaussians per pixel (3-sigma footprints) at every N and every resolution, like a
real scene whose detail grows with its Gaussian count.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import time
from dataclasses import asdict, dataclass
from typing import Callable, Dict, List, Tuple

#: OpenMP threads sleep instead of spinning between parallel regions (set before torch loads).
#: With other processes on the same cores, spinning threads made small ops ~20x slower here.
OMP_WAIT_POLICY = "PASSIVE"
os.environ.setdefault("OMP_WAIT_POLICY", OMP_WAIT_POLICY)

import torch  # noqa: E402
from rich.table import Table  # noqa: E402

from nerfstudio.utils.rich_utils import CONSOLE  # noqa: E402

from edygs_ns.render.cpu_backend import compiled_available, rasterize_cpu  # noqa: E402
from edygs_ns.render.torch_backend import rasterize_torch  # noqa: E402

#: Gaussian counts and square image sizes of the default grid.
DEFAULT_COUNTS = (1_000, 5_000, 20_000, 100_000)
DEFAULT_SIZES = (64, 128, 400)
#: Gaussians covering an average pixel (3-sigma footprints).
DEFAULT_COMPLEXITY = 35.0
#: nearest and farthest depth of the scene, world units.
DEPTH_RANGE = (2.0, 6.0)
#: focal length as a fraction of the image width (53 degree horizontal field of view).
FOCAL_FRACTION = 1.0
#: log-normal spread of the per-axis scales.
SCALE_LOG_STD = 0.5
#: spread of opacity logits.
OPACITY_LOGIT_STD = 1.5
#: feature channels rendered (RGB + motion mask).
CHANNELS = 4


@dataclass
class Record:
    """One timing; wall-clock medians, plus process CPU time (robust to other processes' load)."""

    backend: str
    n_gaussians: int
    width: int
    height: int
    forward_ms: float
    forward_backward_ms: float
    forward_cpu_ms: float
    forward_backward_cpu_ms: float
    threads: int
    load_average: float


def make_scene(n: int, size: int, complexity: float, device: torch.device, seed: int = 0) -> Dict[str, torch.Tensor]:
    """A random scene of n Gaussians in front of one camera of size x size pixels."""
    g = torch.Generator().manual_seed(seed)
    focal = FOCAL_FRACTION * size
    near, far = DEPTH_RANGE
    z = near + (far - near) * torch.rand(n, generator=g)
    half = 0.5 * size / focal
    xy = (torch.rand(n, 2, generator=g) * 2 - 1) * half * z[:, None]
    means = torch.cat([xy, z[:, None]], dim=1)
    # pixel sigma s solves n * pi * (3 s)^2 = complexity * pixels; world sigma = s * z / focal
    sigma_px = math.sqrt(complexity * size * size / (n * math.pi * 9.0))
    world = sigma_px * z[:, None] / focal
    scales = world * torch.exp(SCALE_LOG_STD * torch.randn(n, 3, generator=g) - 0.5 * SCALE_LOG_STD**2)
    scene = {
        "means": means,
        "quats": torch.randn(n, 4, generator=g),
        "scales": scales,
        "opacities": torch.sigmoid(OPACITY_LOGIT_STD * torch.randn(n, generator=g)),
        "features": torch.rand(n, CHANNELS, generator=g),
        "viewmats": torch.eye(4)[None],
        "Ks": torch.tensor([[[focal, 0.0, size / 2], [0.0, focal, size / 2], [0.0, 0.0, 1.0]]]),
    }
    return {k: v.to(device) for k, v in scene.items()}


def _time(fn: Callable[[], object], repeats: int, sync: Callable[[], None]) -> Tuple[float, float]:
    """Median wall-clock and median process CPU milliseconds of fn."""
    fn()  # warm-up
    sync()
    wall, cpu = [], []
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        fn()
        sync()
        wall.append(1e3 * (time.perf_counter() - start))
        cpu.append(1e3 * (time.process_time() - start_cpu))
    return statistics.median(wall), statistics.median(cpu)


def measure(backend: str, n: int, size: int, complexity: float, repeats: int) -> Record:
    """Median forward and forward+backward times in milliseconds."""
    device = torch.device("cuda" if backend == "gsplat" else "cpu")
    if backend == "gsplat":
        from edygs_ns.render.gsplat_backend import rasterize_gsplat as raster
    else:
        raster = {"torch": rasterize_torch, "cpu": rasterize_cpu}[backend]
    scene = make_scene(n, size, complexity, device)
    leaves = {k: v.clone().requires_grad_(k not in ("Ks",)) for k, v in scene.items()}
    weights = torch.rand(1, size, size, CHANNELS, device=device)
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)

    def forward() -> torch.Tensor:
        out = raster(
            leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"], leaves["features"],
            leaves["viewmats"], leaves["Ks"], size, size,
        )
        return (out.render * weights).sum() + out.depth.mean() + out.alpha.mean()

    def forward_backward() -> None:
        forward().backward()
        for v in leaves.values():
            v.grad = None

    fwd, fwd_cpu = _time(forward, repeats, sync)
    fwd_bwd, fwd_bwd_cpu = _time(forward_backward, repeats, sync)
    return Record(
        backend, n, size, size, round(fwd, 2), round(fwd_bwd, 2), round(fwd_cpu, 2), round(fwd_bwd_cpu, 2),
        torch.get_num_threads(), round(os.getloadavg()[0], 2),
    )


def parse_cases(cases: List[str]) -> List[Tuple[int, int]]:
    """'20000x128' -> (20000, 128)."""
    out = []
    for case in cases:
        n, _, size = case.partition("x")
        if not n.isdigit() or not size.isdigit():
            raise ValueError(f"--cases: {case!r} is not N x SIZE, e.g. 20000x128")
        out.append((int(n), int(size)))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True, help="JSON file for the records")
    parser.add_argument("--repeats", type=int, default=5, help="timed runs per case (median reported)")
    parser.add_argument("--complexity", type=float, default=DEFAULT_COMPLEXITY, help="Gaussians per pixel")
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="torch CPU thread counts")
    parser.add_argument("--backends", nargs="+", default=None, help="torch, cpu, gsplat (default: all available)")
    parser.add_argument("--cases", nargs="*", default=None, help="NxSIZE cases (default: full grid)")
    args = parser.parse_args()
    cases = parse_cases(args.cases) if args.cases else [(n, s) for n in DEFAULT_COUNTS for s in DEFAULT_SIZES]
    backends = args.backends or (
        ["torch"] + (["cpu"] if compiled_available() else []) + (["gsplat"] if torch.cuda.is_available() else [])
    )
    load = os.getloadavg()
    CONSOLE.log(
        f"backends={backends} threads={args.threads} OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY')} "
        f"load average (1, 5, 15 min)={load[0]:.2f} {load[1]:.2f} {load[2]:.2f}"
    )
    records: List[Record] = []
    for threads in args.threads:
        torch.set_num_threads(threads)
        for n, size in cases:
            for backend in backends:
                rec = measure(backend, n, size, args.complexity, args.repeats)
                CONSOLE.log(
                    f"{backend} threads={threads} N={n} {size}x{size}: forward {rec.forward_ms} ms (cpu "
                    f"{rec.forward_cpu_ms}), forward+backward {rec.forward_backward_ms} ms (cpu "
                    f"{rec.forward_backward_cpu_ms}), load {rec.load_average}"
                )
                records.append(rec)
    CONSOLE.print(ratio_table(records, args.repeats))
    with open(args.out, "w", encoding="utf-8") as f:
        json.dump([asdict(r) for r in records], f, indent=1)


def ratio_table(records: List[Record], repeats: int) -> Table:
    """One row per record, with the torch backend's time over this one's (same case and threads)."""
    reference = {(r.n_gaussians, r.width, r.threads): r for r in records if r.backend == "torch"}
    table = Table(title=f"rasteriser timings, median of {repeats} (ms); x torch = torch time / this time")
    for col in ("backend", "threads", "N", "image", "forward", "fwd+bwd", "fwd cpu", "fwd+bwd cpu", "x torch fwd",
                "x torch fwd+bwd", "load"):
        table.add_column(col, justify="right")
    for r in records:
        ref = reference.get((r.n_gaussians, r.width, r.threads))
        ratios = (f"{ref.forward_ms / r.forward_ms:.1f}", f"{ref.forward_backward_ms / r.forward_backward_ms:.1f}") if ref else ("-", "-")
        table.add_row(
            r.backend, str(r.threads), str(r.n_gaussians), f"{r.width}x{r.height}", f"{r.forward_ms:.1f}",
            f"{r.forward_backward_ms:.1f}", f"{r.forward_cpu_ms:.1f}", f"{r.forward_backward_cpu_ms:.1f}", *ratios,
            f"{r.load_average:.2f}",
        )
    return table


if __name__ == "__main__":
    main()
