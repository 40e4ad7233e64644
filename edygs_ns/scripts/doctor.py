"""`edygs-doctor`: is the CUDA path ready? torch, CUDA runtime, toolkit, GPU arch, gsplat's kernels.

Prints one line per component, then a diagnosis and the fix. ``--build-gsplat`` builds gsplat's
CUDA extension ahead of time (no GPU needed: ``--arch`` names the target, e.g. 9.0 for
H100/H200), so the first ``ns-train edygs`` on CUDA does not start a long JIT build. The logic
is in ``edygs_ns.cuda_setup``.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import tyro


@dataclass
class DoctorCommand:
    """Report the CUDA path's state (and build gsplat's kernels ahead of time with --build-gsplat)."""

    build_gsplat: bool = False
    """build gsplat's CUDA extension now (BUILD_TIME: about 40-60 min on 2 cores, minutes on 16)"""
    arch: Optional[str] = None
    """TORCH_CUDA_ARCH_LIST to build for, e.g. 9.0 (H100/H200) or '8.6;9.0'; default the GPU's, else 9.0"""
    jobs: Optional[int] = None
    """MAX_JOBS for the build; default one per core (at most one per 2 GiB of memory)"""
    extensions_dir: Optional[Path] = None
    """TORCH_EXTENSIONS_DIR: build into this folder (its gsplat_cuda/) instead of torch's cache"""
    dry_run: bool = False
    """with --build-gsplat: print the build's command and environment, build nothing"""
    json_out: Optional[Path] = None
    """also write the report and diagnosis here as JSON"""

    def main(self) -> int:
        """Print the report; returns the exit status (1 when the build fails)."""
        from edygs_ns import cuda_setup

        report = cuda_setup.collect_report()
        verdicts = cuda_setup.diagnose(report)
        print(cuda_setup.format_report(report, verdicts), flush=True)
        if self.json_out is not None:
            self.json_out.parent.mkdir(parents=True, exist_ok=True)
            self.json_out.write_text(json.dumps(cuda_setup.report_dict(report, verdicts), indent=2) + "\n")
        if not self.build_gsplat:
            return 0
        try:
            plan = cuda_setup.build_plan(self.arch, self.jobs, self.extensions_dir, gpu_arch=report.gpu_arch)
        except ValueError as exc:
            print(f"build-gsplat: {exc}", file=sys.stderr)
            return 1
        print(f"build-gsplat: sm {plan.arch} ({plan.arch_source}), MAX_JOBS={plan.jobs}, into {plan.build_dir}")
        print(f"  {plan.shell()}", flush=True)
        if self.dry_run:
            return 0
        try:
            where = cuda_setup.run_build(plan)
        except RuntimeError as exc:
            print(f"build-gsplat: {exc}", file=sys.stderr)
            return 1
        print(f"build-gsplat: done; {where} imports (stamp {cuda_setup.BUILD_STAMP})")
        return 0


def entrypoint() -> None:
    """Console script `edygs-doctor`."""
    sys.exit(tyro.cli(DoctorCommand).main())


if __name__ == "__main__":
    entrypoint()
