"""Per-view metric values accumulated over an evaluation; the metrics themselves are in
:mod:`edygs_ns.losses.metrics` (the model computes them too)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Dict, List, Mapping


@dataclass
class MetricSet:
    """Per-view metric values, accumulated view by view, summarised by mean and std.

    Attributes:
        values: metric name -> list of per-view values, in the order they were added.
    """

    values: Dict[str, List[float]] = field(default_factory=dict)

    def add(self, name: str, value: float) -> None:
        """Append one view's value of metric `name`."""
        self.values.setdefault(name, []).append(float(value))

    def update(self, metrics: Mapping[str, float]) -> None:
        """Append one view's values of several metrics, e.g. {"psnr": 31.2, "ssim": 0.91}."""
        for name, value in metrics.items():
            self.add(name, value)

    def _get(self, name: str) -> List[float]:
        if name not in self.values or not self.values[name]:
            raise KeyError(f"MetricSet has no values for {name!r}; it holds {sorted(self.values)}")
        return self.values[name]

    def count(self, name: str) -> int:
        """Number of views holding a value of `name` (0 if none)."""
        return len(self.values.get(name, []))

    def mean(self, name: str) -> float:
        """Mean over views of metric `name` (inf if any value is inf, as PSNR of a perfect view)."""
        vals = self._get(name)
        return float(sum(vals) / len(vals))

    def std(self, name: str) -> float:
        """Population standard deviation (ddof = 0) over views of metric `name`."""
        vals = self._get(name)
        mu = self.mean(name)
        if math.isinf(mu):
            return math.nan
        return float(math.sqrt(sum((v - mu) ** 2 for v in vals) / len(vals)))

    def summary(self) -> Dict[str, Dict[str, float]]:
        """{name: {"mean": ..., "std": ..., "n": ...}} for every metric with at least one value."""
        return {
            name: {"mean": self.mean(name), "std": self.std(name), "n": self.count(name)}
            for name in self.values
            if self.values[name]
        }
