"""The resumable step runner of ``edygs-process``: progress bars, timing, reuse, --overwrite.

Every step has a name and a fingerprint (a hash of its inputs: input files' size and mtime,
the settings it depends on, and the fingerprint of the step before it). The output folder keeps
a record of finished steps (:data:`STEP_RECORD_NAME`). Running again on the same folder:

- a step whose record has the same fingerprint is reused (not run again);
- a step not yet finished runs;
- a finished step whose fingerprint changed is an error without ``--overwrite`` (redoing it
  would replace what is there); with ``--overwrite`` every step runs again.

A folder that exists, is not empty and holds no step record belongs to someone else: it is an
error without ``--overwrite``; with it, only the entries this command writes are removed.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, Optional, Sequence

from nerfstudio.utils.rich_utils import CONSOLE
from rich.progress import BarColumn, MofNCompleteColumn, Progress, SpinnerColumn, TextColumn, TimeElapsedColumn, TimeRemainingColumn

#: The record of finished steps, in the output folder.
STEP_RECORD_NAME = ".edygs_steps.json"
#: Version of the record's format; a record of another version is not trusted for reuse.
STEP_RECORD_VERSION = 1
#: Characters of the sha256 hex digest kept as a fingerprint.
FINGERPRINT_CHARS = 16


def fingerprint(*parts: Any) -> str:
    """A short stable hash of JSON-serialisable parts (paths and other objects become strings)."""
    text = json.dumps(parts, sort_keys=True, default=str)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:FINGERPRINT_CHARS]


def file_signature(path: Path) -> Dict[str, Any]:
    """What identifies a file's content cheaply: absolute path, size, modification time (ns).

    Folders are described by the signatures of every file under them (sorted).
    """
    path = Path(path).resolve()
    if path.is_dir():
        return {"path": str(path), "files": [file_signature(p) for p in sorted(path.rglob("*")) if p.is_file()]}
    if not path.exists():
        return {"path": str(path), "missing": True}
    stat = path.stat()
    return {"path": str(path), "size": stat.st_size, "mtime_ns": stat.st_mtime_ns}


@contextmanager
def progress_bar(description: str, total: Optional[int]) -> Iterator[Callable[..., None]]:
    """A rich progress bar on nerfstudio's console; yields ``advance(n=1)``.

    Args:
        description: text left of the bar.
        total: number of units, or None for an open-ended spinner with elapsed time.
    """
    columns = [SpinnerColumn(), TextColumn(description), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn()]
    if total is not None:
        columns.append(TimeRemainingColumn())
    with Progress(*columns, console=CONSOLE, transient=False) as progress:
        task = progress.add_task(description, total=total)
        done = [0]

        def advance(n: int = 1) -> None:
            step = n if total is None else max(0, min(n, total - done[0]))  # never past the total
            done[0] += step
            progress.advance(task, step)

        yield advance


def _write_json_atomic(path: Path, data: Any) -> None:
    tmp = path.with_name(path.name + ".partial")
    tmp.write_text(json.dumps(data, indent=2))
    os.replace(tmp, path)


@dataclass
class StepOutcome:
    """How one step went.

    Attributes:
        name: the step.
        seconds: wall time of the run that produced it (the original run when reused).
        summary: its one-line summary.
        reused: True when a finished step was found and not run again.
    """

    name: str
    seconds: float
    summary: str
    reused: bool


class StepRunner:
    """Runs named steps into one output folder, reusing finished ones.

    Args:
        output: the output folder.
        owned: names of the entries (files/folders) of ``output`` this command writes; the
            only ones ``--overwrite`` removes.
        overwrite: redo every step and replace what is there.
    """

    def __init__(self, output: Path, owned: Sequence[str], overwrite: bool) -> None:
        self.output = Path(output)
        self.owned = tuple(owned) + (STEP_RECORD_NAME,)
        self.overwrite = overwrite
        self.outcomes: List[StepOutcome] = []
        self._record: Dict[str, Any] = {"version": STEP_RECORD_VERSION, "steps": {}}

    @property
    def record_path(self) -> Path:
        return self.output / STEP_RECORD_NAME

    def prepare(self, inputs: Sequence[Path] = ()) -> None:
        """Check the output folder, load its record, or clear it with --overwrite.

        Args:
            inputs: input files/folders; none may lie inside the output folder.

        Raises:
            ValueError: an input lies inside the output folder.
            FileExistsError: the folder holds something else, or a record of another version,
                and --overwrite was not given.
        """
        out = self.output.resolve()
        for path in inputs:
            resolved = Path(path).resolve()
            if resolved == out or out in resolved.parents:
                raise ValueError(f"{self.output}: the output folder contains the input {path}; choose another output folder")
        if self.output.exists() and not self.output.is_dir():
            raise FileExistsError(f"{self.output}: exists and is not a folder")
        has_content = self.output.is_dir() and any(self.output.iterdir())
        if self.overwrite:
            self.clear()
        elif self.record_path.is_file():
            record = json.loads(self.record_path.read_text())
            if record.get("version") != STEP_RECORD_VERSION:
                raise FileExistsError(
                    f"{self.record_path}: step record of version {record.get('version')} (this is {STEP_RECORD_VERSION}); "
                    "pass --overwrite to process again"
                )
            self._record = record
        elif has_content:
            raise FileExistsError(
                f"{self.output}: folder exists and holds files edygs-process did not write; "
                "choose another output folder or pass --overwrite (which removes only edygs-process's own entries)"
            )
        self.output.mkdir(parents=True, exist_ok=True)

    def clear(self, names: Optional[Sequence[str]] = None) -> None:
        """Remove the owned entries (or the given subset of them) from the output folder."""
        for name in self.owned if names is None else names:
            path = self.output / name
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path)
            elif path.exists() or path.is_symlink():
                path.unlink()
        if names is None:
            self._record = {"version": STEP_RECORD_VERSION, "steps": {}}

    def finished(self, name: str) -> Optional[Dict[str, Any]]:
        """The record of a finished step, or None."""
        return self._record["steps"].get(name)

    def run(self, name: str, step_fingerprint: str, fn: Callable[[], str]) -> StepOutcome:
        """Run a step unless it is finished with the same fingerprint.

        Args:
            name: the step's name.
            step_fingerprint: hash of everything the step's result depends on.
            fn: does the work and returns a one-line summary.

        Returns:
            The outcome (also appended to ``self.outcomes``).

        Raises:
            FileExistsError: the step finished earlier with another fingerprint and --overwrite
                was not given.
        """
        done = self.finished(name)
        if done is not None and done.get("fingerprint") == step_fingerprint:
            outcome = StepOutcome(name, float(done["seconds"]), str(done["summary"]), reused=True)
            CONSOLE.print(f"[cyan]↺ {name}[/]: reused — {outcome.summary} [dim](took {outcome.seconds:.1f} s)[/]")
            self.outcomes.append(outcome)
            return outcome
        if done is not None:
            raise FileExistsError(
                f"{self.output}: step '{name}' was finished with other inputs or settings; redoing it would replace "
                "the processed scene there. Pass --overwrite to process again, or choose another output folder"
            )
        start = time.perf_counter()
        try:
            summary = fn()
        except BaseException:
            CONSOLE.print(f"[bold red]✗ {name}[/]: failed after {time.perf_counter() - start:.1f} s")
            raise
        seconds = time.perf_counter() - start
        self._record["steps"][name] = {
            "fingerprint": step_fingerprint,
            "seconds": seconds,
            "summary": summary,
            "finished_at": time.strftime("%Y-%m-%dT%H:%M:%S"),
        }
        _write_json_atomic(self.record_path, self._record)
        CONSOLE.print(f"[bold green]✓ {name}[/]: {summary} [dim]({seconds:.1f} s)[/]")
        outcome = StepOutcome(name, seconds, summary, reused=False)
        self.outcomes.append(outcome)
        return outcome
