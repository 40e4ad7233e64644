"""`edygs-synth`: write the built-in synthetic dynamic scene as a raw capture (docs/layouts.md).

The scene writer is :mod:`edygs_ns.sim.writer`; this is its command line.
"""

from __future__ import annotations

import json

import tyro
from nerfstudio.utils.rich_utils import CONSOLE

from edygs_ns.sim.writer import SynthConfig, write_synthetic_scene


def entrypoint() -> None:
    """Console script `edygs-synth`."""
    config = tyro.cli(SynthConfig)
    folder = write_synthetic_scene(config)
    summary = json.loads((folder / "scene.json").read_text())
    CONSOLE.print(f"edygs-synth: {config.n_frames} blurry frames, {summary['n_events']:,} events, "
                  f"{config.n_frames * config.k} latents -> {folder}")


if __name__ == "__main__":
    entrypoint()
