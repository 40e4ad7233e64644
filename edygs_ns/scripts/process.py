"""``edygs-process``: from a raw capture to a trainable scene (docs/layouts.md).

The steps (read, EDI, poses, write) are :mod:`edygs_ns.preprocess.pipeline`; this is its command line.
"""

from __future__ import annotations

import sys

import tyro
from nerfstudio.utils.rich_utils import CONSOLE

from edygs_ns.preprocess.pipeline import ProcessConfig, RegistrationError, process

#: Exit status after Ctrl-C (128 + SIGINT, as shells report it).
INTERRUPTED_EXIT_CODE = 130


def entrypoint() -> None:
    """Console script ``edygs-process``."""
    config = tyro.cli(ProcessConfig)
    try:
        report = process(config)
    except (RegistrationError, OSError, ValueError) as err:  # OSError: FileExistsError, FileNotFoundError, I/O
        CONSOLE.print(f"[bold red]edygs-process failed:[/] {err}", soft_wrap=True)
        sys.exit(1)
    except KeyboardInterrupt:
        CONSOLE.print("[bold red]edygs-process interrupted:[/] finished steps are kept; run the same command again to resume")
        sys.exit(INTERRUPTED_EXIT_CODE)
    interpolated = len(report["interpolated_latents"])
    CONSOLE.print(
        f"[bold]edygs-process[/]: {report['registered_latents']}/{report['total_latents']} latents posed by "
        f"{report['pose_source']}" + (f", {interpolated} interpolated in time" if interpolated else "")
        + f", {report['num_points']:,} points -> {config.output}"
    )


if __name__ == "__main__":
    entrypoint()
