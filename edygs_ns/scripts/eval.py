"""`edygs-eval`: evaluate a trained EDyGS run (deblurring, novel views, motion masks, poses).

    edygs-eval --load-config RUN/config.yml --output DIR [--lpips-weights PATH] [--split both]

Writes DIR/metrics.json, DIR/metrics.md, grids, a trajectory plot and PSNR-over-time curves and
prints the markdown table; edygs_ns.eval.evaluate documents every output and the protocol.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, Optional

import tyro

from edygs_ns.eval.evaluate import DEFAULT_MAX_GRIDS, EvalSplit, evaluate_run
from edygs_ns.eval.novel_pose_fit import NovelPoseFitConfig


@dataclass
class EvalCommand:
    """Evaluate a trained EDyGS run against the scene's ground truth."""

    load_config: Path
    """The run's config.yml (written by ns-train)."""
    output: Path = Path("eval")
    """Folder for metrics.json, metrics.md and the figures (created)."""
    lpips_weights: Optional[Path] = None
    """torchvision ImageNet backbone weights for LPIPS (a .pth file or a folder holding
    alexnet-owt-7be5be79.pth / vgg16-397923af.pth); without them LPIPS is reported unavailable."""
    split: EvalSplit = "both"
    """input: deblurring of the training latents; novel: the ground-truth novel views; both."""
    max_grids: int = DEFAULT_MAX_GRIDS
    """Views per split drawn as comparison grids, evenly spaced (negative: all, 0: none)."""
    align_novel: bool = True
    """Move the ground-truth novel cameras into the model's frame by the Sim(3) fitted between
    the ground-truth and the refined training poses before rendering them."""
    novel_pose_fit: NovelPoseFitConfig = field(default_factory=NovelPoseFitConfig)
    """Then fit each novel camera's pose to its image with the model frozen (the protocol of
    pose-estimating NeRF/3DGS papers); --novel-pose-fit.steps 0 scores the aligned poses as they are."""
    method: Optional[str] = None
    """Row label of the run in the table; default its method name."""

    def main(self) -> Dict[str, Any]:
        """Run the evaluation; returns the metrics written to metrics.json."""
        return evaluate_run(
            self.load_config, self.output, lpips_weights=self.lpips_weights, split=self.split,
            max_grids=self.max_grids, align_novel=self.align_novel, method=self.method,
            novel_pose_fit=self.novel_pose_fit,
        )  # fmt: skip


def entrypoint() -> None:
    """Console script `edygs-eval`."""
    tyro.cli(EvalCommand).main()


if __name__ == "__main__":
    entrypoint()
