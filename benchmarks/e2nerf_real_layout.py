"""Write a raw capture of ``edygs-synth`` in E2NeRF's real-data layout (with its ground truth in gt/).

    python benchmarks/e2nerf_real_layout.py RAW OUT

Then ``edygs-process --e2nerf OUT ...`` processes it (copying gt/ for ``edygs-eval``), or
``ns-train ... --data OUT`` reads it directly. See edygs_ns/preprocess/e2nerf_writer.py.
"""

from __future__ import annotations

import sys
from pathlib import Path

from edygs_ns.preprocess.e2nerf_writer import write_e2nerf_real


def main() -> None:
    if len(sys.argv) != 3:
        raise SystemExit(__doc__)
    try:
        print(f"wrote {write_e2nerf_real(Path(sys.argv[1]), Path(sys.argv[2]))}")
    except (OSError, ValueError) as err:
        raise SystemExit(f"e2nerf_real_layout: {err}")


if __name__ == "__main__":
    main()
