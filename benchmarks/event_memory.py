"""Peak memory and events/s of edygs-process's event stages on an event file larger than memory.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/event_memory.py --events 100000000 --dir /tmp/edygs_event_memory

1. ``write``: an HDF5 file of N uniformly random events in the project's events.h5 layout
   (:class:`edygs_ns.events.writers.H5EventWriter`, chunk by chunk, never all in memory), a
   matching exposure table (346x260 sensor, ``--exposures`` frames evenly spread over the events,
   each exposed half of its period) and its grey PNG frames.
2. ``process`` (once per ``--chunk-events`` value; 0 = each exposure's whole window at once, as
   edygs-process read before it was chunked), in a fresh subprocess, the stages of edygs-process
   that touch events, through the same library calls:

   - ``read``: :func:`edygs_ns.preprocess.inputs.load_capture` (frames, opening the event file
     with its whole-file sortedness and NaN/inf scan, time-unit detection, coverage);
   - ``bin + Θ equations``: :func:`edygs_ns.events.stream.bin_exposure` per exposure into a
     memory-mapped ``event_maps.npy`` (the EDI inputs), feeding the Θ accumulator;
   - ``Θ fit``: :meth:`ContrastAccumulator.estimate` and :func:`choose_theta`.

Each stage's peak resident memory is measured inside the child (the kernel's VmHWM, reset before
the stage through /proc/self/clear_refs); the child's peak is the largest of them (the reset also
resets the ru_maxrss that ``wait4`` reports, so that is used only for the writing child, which
resets nothing). Events/s: the events a stage goes through (every event for ``read``, those inside
the exposures' read spans for binning) over its wall time. The files are deleted at the end
unless ``--keep``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Dict, List

import numpy as np

SENSOR = (260, 346)  # (height, width) of a DAVIS346
KIB = 1024


def _status_kib(field: str) -> int:
    """A memory field of /proc/self/status (VmHWM, VmRSS), KiB."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    return -1


def _reset_peak() -> bool:
    """Reset VmHWM to the current RSS (Linux >= 4.0); False where not allowed."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


# ------------------------------------------------------------------------------------- write


def write_inputs(folder: Path, n_events: int, exposure_counts: List[int], duration_us: int, chunk: int, seed: int) -> Dict:
    """events.h5 (n_events, chunk by chunk), exposures_<n>.csv per count n and the frames; returns what was written."""
    from PIL import Image

    from edygs_ns.events.exposures import Exposure, write_exposures
    from edygs_ns.events.types import EventArray
    from edygs_ns.events.writers import H5EventWriter

    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    h, w = SENSOR
    n_chunks = max(1, -(-n_events // chunk))
    start = time.perf_counter()
    with H5EventWriter(folder / "events.h5", SENSOR, overwrite=True) as writer:
        for j in range(n_chunks):
            m = min(chunk, n_events - j * chunk)
            t0, t1 = j * duration_us // n_chunks, (j + 1) * duration_us // n_chunks  # slabs: sorted overall
            writer.append(EventArray(
                x=rng.integers(0, w, m, dtype=np.int32), y=rng.integers(0, h, m, dtype=np.int32),
                t=np.sort(rng.integers(t0, t1, m, dtype=np.int64)),
                p=(2 * rng.integers(0, 2, m, dtype=np.int8) - 1).astype(np.int8), sensor_size=SENSOR,
            ))
    seconds = time.perf_counter() - start
    gradient = np.linspace(60, 190, w, dtype=np.float64)[None, :, None]
    frames = []
    for i in range(max(exposure_counts)):
        frames.append(folder / "frames" / f"{i:04d}.png")
        frames[-1].parent.mkdir(exist_ok=True)
        level = gradient + 10 * np.sin(i / 3.0)
        Image.fromarray(np.broadcast_to(level, (h, w, 3)).astype(np.uint8)).save(frames[-1])
    for n in exposure_counts:  # evenly spread over the events, each exposed for half its period
        period = duration_us // n
        exposures = [Exposure(i, i * period + period // 4, i * period + 3 * period // 4, frames[i]) for i in range(n)]
        write_exposures(folder / f"exposures_{n}.csv", exposures, folder)
    return {"seconds": seconds, "bytes": (folder / "events.h5").stat().st_size}


# ------------------------------------------------------------------------------------ process


def process_stages(folder: Path, n_exposures: int, k: int, chunk_events: int) -> Dict:
    """The event stages of edygs-process (see the module docstring); per stage: seconds, events, peak KiB."""
    from edygs_ns.events.color import decode_to_linear
    from edygs_ns.events.contrast import ContrastAccumulator, choose_theta
    from edygs_ns.events.edi import EdiConfig
    from edygs_ns.events.stream import bin_exposure
    from edygs_ns.preprocess.inputs import InputConfig, load_capture

    stages: List[Dict] = []
    baseline = _status_kib("VmRSS")

    def stage(name: str, seconds: float, events: int) -> None:
        stages.append({"stage": name, "seconds": seconds, "events": events, "peak_kib": _status_kib("VmHWM"),
                       "rss_after_kib": _status_kib("VmRSS")})

    _reset_peak()
    start = time.perf_counter()
    capture = load_capture(InputConfig(exposures=folder / f"exposures_{n_exposures}.csv", events=folder / "events.h5"), k, False)
    n_events = len(capture.events)
    stage("read (frames, open + whole-file order/NaN scan, unit, coverage)", time.perf_counter() - start, n_events)

    _reset_peak()
    exposures = capture.exposures
    n, (h, w) = len(exposures), capture.events.sensor_size
    color_space = EdiConfig().color_space
    maps = np.lib.format.open_memmap(folder / "event_maps.npy", mode="w+", dtype=np.float32, shape=(n, k - 1, h, w))
    contrast = ContrastAccumulator(n)
    source = _Counting(capture.events)
    start = time.perf_counter()
    for i in range(n):
        frame = decode_to_linear(capture.frames[i] / 255.0, color_space)
        maps[i] = bin_exposure(source, exposures, i, k, capture.event_count_scale, contrast, frame,
                               max_events=chunk_events)
    seconds = time.perf_counter() - start
    maps.flush()
    del maps
    stage("bin + Θ equations (EDI event maps, per exposure)", seconds, source.events_read)

    _reset_peak()
    start = time.perf_counter()
    estimate = contrast.estimate()
    choice = choose_theta(estimate, None, contrast.reason())
    stage("Θ fit", time.perf_counter() - start, 0)
    capture.close()
    return {"baseline_rss_kib": baseline, "events": n_events, "exposures": n, "k": k, "chunk_events": chunk_events,
            "theta_line": choice.line(), "stages": stages}


class _Counting:
    """An event source that counts the events its chunks hand out."""

    def __init__(self, base) -> None:
        self.base, self.name, self.sensor_size, self.events_read = base, base.name, base.sensor_size, 0

    def chunks(self, t_start_us: int, t_end_us: int, max_events: int):
        for chunk in self.base.chunks(t_start_us, t_end_us, max_events):
            self.events_read += len(chunk)
            yield chunk


# ---------------------------------------------------------------------------------- parent


def _run_child(args: List[str]) -> Dict:
    """Run this script as a child; its JSON result plus wait4's ru_maxrss (KiB; since its last peak reset)."""
    out_path = Path(args[args.index("--result") + 1])
    proc = subprocess.Popen([sys.executable, __file__] + args)
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise SystemExit(f"child {' '.join(args)} failed with status {proc.returncode}")
    result = json.loads(out_path.read_text())
    result["child_max_rss_kib"] = usage.ru_maxrss
    return result


def _mib(kib: float) -> str:
    return f"{kib / KIB:,.0f} MiB"


def main() -> None:
    from edygs_ns.events.readers import READ_CHUNK_EVENTS

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--events", type=float, default=1e8, help="events in the file (default 1e8)")
    parser.add_argument("--exposures", type=int, nargs="+", default=[40, 4],
                        help="frames in the exposure table; one run per value (fewer: more events per exposure window)")
    parser.add_argument("--duration-s", type=float, default=10.0, help="seconds the events span")
    parser.add_argument("--k", type=int, default=5, help="latents per frame (k - 1 event bins)")
    parser.add_argument("--chunk-events", type=int, nargs="+", default=[READ_CHUNK_EVENTS, 0],
                        help="read chunk sizes to measure (0: each exposure's whole window at once)")
    parser.add_argument("--write-chunk", type=int, default=1 << 22, help="events generated and appended at once")
    parser.add_argument("--dir", type=Path, default=Path("/tmp/edygs_event_memory"), help="where the files go")
    parser.add_argument("--keep", action="store_true", help="keep the files")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--child", choices=["write", "process"], help=argparse.SUPPRESS)
    parser.add_argument("--result", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    n_events = int(args.events)

    if args.child == "write":
        result = write_inputs(args.dir, n_events, args.exposures, int(args.duration_s * 1e6), args.write_chunk, args.seed)
        args.result.write_text(json.dumps(result))
        return
    if args.child == "process":
        args.result.write_text(json.dumps(process_stages(args.dir, args.exposures[0], args.k, args.chunk_events[0])))
        return

    free = shutil.disk_usage(args.dir.parent if not args.dir.exists() else args.dir).free
    print(f"event_memory: {n_events:,} events, {'/'.join(map(str, args.exposures))} exposures over {args.duration_s:g} s, sensor "
          f"{SENSOR[1]}x{SENSOR[0]}, k={args.k}; files in {args.dir} ({free / 2**30:.1f} GiB free)", flush=True)
    common = ["--events", str(n_events), "--duration-s", str(args.duration_s),
              "--k", str(args.k), "--dir", str(args.dir), "--seed", str(args.seed), "--write-chunk", str(args.write_chunk)]
    args.dir.mkdir(parents=True, exist_ok=True)
    try:
        written = _run_child(common + ["--exposures", *map(str, args.exposures), "--child", "write",
                                       "--result", str(args.dir / "write.json")])
        print(f"write: {written['bytes'] / 2**30:.2f} GiB HDF5 in {written['seconds']:.1f} s "
              f"({n_events / written['seconds'] / 1e6:.2f} M events/s), peak RSS {_mib(written['child_max_rss_kib'])}",
              flush=True)
        for n_exp, chunk in [(n, c) for n in args.exposures for c in args.chunk_events]:
            result = _run_child(common + ["--exposures", str(n_exp), "--child", "process", "--chunk-events", str(chunk),
                                          "--result", str(args.dir / f"process_{n_exp}_{chunk}.json")])
            label = f"read chunks of {chunk:,} events" if chunk > 0 else "each exposure's whole window at once (old route)"
            per_window = n_events / n_exp / 2 ** 20
            base = result["baseline_rss_kib"]
            peak = max(s["peak_kib"] for s in result["stages"])
            print(f"\nprocess, {n_exp} exposures (~{per_window:.1f} Mi events per read span), {label}: peak RSS "
                  f"{_mib(peak)}, {_mib(peak - base)} above the {_mib(base)} after imports (torch, nerfstudio)")
            print(f"  {'stage':<66} {'seconds':>8} {'M events/s':>11} {'peak RSS':>10} {'- imports':>10}")
            for s in result["stages"]:
                rate = f"{s['events'] / s['seconds'] / 1e6:.2f}" if s["events"] else "-"
                print(f"  {s['stage']:<66} {s['seconds']:8.1f} {rate:>11} {_mib(s['peak_kib']):>10} "
                      f"{_mib(s['peak_kib'] - base):>10}")
            print(f"  {result['theta_line']}", flush=True)
    finally:
        if not args.keep:
            shutil.rmtree(args.dir, ignore_errors=True)


if __name__ == "__main__":
    main()
