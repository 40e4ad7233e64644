"""Throughput of bin_events on synthetic events: `python benchmarks/event_binning.py --help`."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import tyro
from nerfstudio.utils.rich_utils import CONSOLE

from edygs_ns.events.accumulate import bin_events, latent_times_us
from edygs_ns.events.types import EventArray


@dataclass
class BinningBenchmark:
    """Bin uniformly random events into k-1 bins and report events per second."""

    num_events: int = 10_000_000
    """Number of synthetic events."""
    height: int = 260
    """Sensor rows (DAVIS346 by default)."""
    width: int = 346
    """Sensor columns."""
    duration_us: int = 1_000_000
    """Time span of the events, µs."""
    k: int = 5
    """Latent frames: the span is cut into k - 1 bins."""
    repeats: int = 5
    """Timed runs; the best and the median are reported (one untimed warm-up run first)."""
    seed: int = 0
    """Seed of the synthetic events."""

    def make_events(self) -> EventArray:
        """Uniform random pixels, polarities and (sorted) timestamps."""
        rng = np.random.default_rng(self.seed)
        n = self.num_events
        return EventArray(
            x=rng.integers(0, self.width, n, dtype=np.int32),
            y=rng.integers(0, self.height, n, dtype=np.int32),
            t=np.sort(rng.integers(0, self.duration_us, n, dtype=np.int64)),
            p=(2 * rng.integers(0, 2, n, dtype=np.int8) - 1).astype(np.int8),
            sensor_size=(self.height, self.width),
        )

    def main(self) -> None:
        """Run the benchmark and print events per second."""
        events = self.make_events()
        boundaries = latent_times_us(0, self.duration_us, self.k)
        bin_events(events, boundaries)  # warm-up: first-touch page faults of the output buffers
        seconds = []
        for _ in range(self.repeats):
            start = time.perf_counter()
            bins = bin_events(events, boundaries)
            seconds.append(time.perf_counter() - start)
        total = int(np.abs(bins).sum())
        best, median = min(seconds), float(np.median(seconds))
        CONSOLE.print(
            f"bin_events: {self.num_events:,} events, {self.k - 1} bins of {self.height}x{self.width}: "
            f"best {best * 1e3:.1f} ms ({self.num_events / best / 1e6:.1f} M events/s), "
            f"median {median * 1e3:.1f} ms ({self.num_events / median / 1e6:.1f} M events/s); "
            f"|counts| sum {total:,}"
        )


def entrypoint() -> None:
    """CLI entry point."""
    tyro.cli(BinningBenchmark).main()


if __name__ == "__main__":
    entrypoint()
