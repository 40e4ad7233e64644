"""Input-view PSNR of an `edygs-eval` run split by latent index (the instant within each exposure).

The blurry baseline trains on the exposure-centre instant only (latent index k // 2); its score at
the other instants shows whether the geometry holds away from the cameras it saw.

    python benchmarks/per_latent_psnr.py SCENE EVAL/metrics.json

SCENE: the processed scene (its transforms.json gives each latent's time and index).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Dict, List

import numpy as np

#: Rows of metrics.json that are references, not the run.
REFERENCE_ROWS = ("EDI latent", "blurry input")
#: Per-view keys reported.
KEYS = ("psnr", "psnr_static", "psnr_dynamic")


def per_latent(scene: Path, metrics: Path) -> Dict[str, List[float]]:
    """{key: [mean over the views of latent index j, for j = 0 .. k-1]} of the run's input views."""
    try:
        frames = json.loads((scene / "transforms.json").read_text())["frames"]
        rows = json.loads(metrics.read_text())
    except (OSError, ValueError, KeyError) as err:
        raise SystemExit(f"per_latent_psnr: cannot read {scene / 'transforms.json'} or {metrics}: {err}")
    times = np.array([f["time"] for f in frames])
    latent = np.array([f["latent_index"] for f in frames])
    view = next(v for name, v in rows.items() if name not in REFERENCE_ROWS)["input views"]["per_view"]
    index = latent[np.abs(np.asarray(view["time"])[:, None] - times[None]).argmin(axis=1)]  # nearest latent time
    return {key: [float(np.nanmean(np.asarray(view[key], dtype=float)[index == j])) for j in range(int(latent.max()) + 1)]
            for key in KEYS}


def main() -> None:
    if len(sys.argv) != 3:
        raise SystemExit(__doc__)
    for key, values in per_latent(Path(sys.argv[1]), Path(sys.argv[2])).items():
        print(f"{key:13s} " + " ".join(f"j={j}: {v:.2f}" for j, v in enumerate(values)))


if __name__ == "__main__":
    main()
