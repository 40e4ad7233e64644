"""The resumable step runner of ``edygs-process``: progress bars, timing, reuse, --overwrite.

Every step has a name and a fingerprint (a hash of its inputs: input files' size and mtime,
the settings it depends on, and the fingerprint of the step before it). The output folder keeps
a record of finished steps (:data:`STEP_RECORD_NAME`). Running again on the same folder:

- a step whose record has the same fingerprint is reused (not run again);
- a step not yet finished runs;
- a finished step whose fingerprint changed runs again (with every step after it) while the
  folder holds no finished scene (its final step is not recorded: only work products would be
  replaced); once the scene is there it is an error without ``--overwrite``.

Nothing that exists is lost to a failed run: with ``--overwrite`` over an existing scene the
steps build into a staging folder beside the output (``.<name>.edygs-staging``), and only a
run that succeeds swaps its entries in (:meth:`StepRunner.commit`; the old ones pass through
``.<name>.edygs-old`` and are then deleted). Entries this command does not write are never
touched. Leftovers of an interrupted run are cleaned up (or, for an interrupted swap, the old
scene is put back) by the next run, which says so.

A folder that exists, is not empty and holds neither a step record nor only our own scratch
entries (a work folder left by a run interrupted before its first step finished, removed with a
notice) belongs to someone else: it is an error without ``--overwrite``.
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
#: Suffixes of the hidden folders beside the output that an --overwrite run builds in and retires to.
STAGING_SUFFIX = ".edygs-staging"
RETIRED_SUFFIX = ".edygs-old"


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
            only ones ``--overwrite`` replaces.
        overwrite: redo every step; an existing scene is replaced only when the new one is done.
        scratch: owned entries that are intermediate products only (the work folder); without a
            step record they are leftovers of an interrupted run and are removed.
        final_step: the step whose record means a finished scene is in the folder.
    """

    def __init__(
        self, output: Path, owned: Sequence[str], overwrite: bool, scratch: Sequence[str] = (), final_step: str = "write"
    ) -> None:
        self.output = Path(output)
        self.owned = tuple(owned) + (STEP_RECORD_NAME,)
        self.overwrite = overwrite
        self.scratch = tuple(scratch)
        self.final_step = final_step
        self.build = self.output
        self.outcomes: List[StepOutcome] = []
        self._record: Dict[str, Any] = {"version": STEP_RECORD_VERSION, "steps": {}}

    @property
    def record_path(self) -> Path:
        return self.build / STEP_RECORD_NAME

    @property
    def staging(self) -> Path:
        return self.output.parent / f".{self.output.name}{STAGING_SUFFIX}"

    @property
    def retired(self) -> Path:
        return self.output.parent / f".{self.output.name}{RETIRED_SUFFIX}"

    def _present(self, folder: Path) -> List[str]:
        return [n for n in self.owned if (folder / n).exists() or (folder / n).is_symlink()]

    def prepare(self, inputs: Sequence[Path] = ()) -> Path:
        """Check the output folder, clean leftovers, load its record; choose where the steps write.

        Args:
            inputs: input files/folders; none may lie inside the output folder.

        Returns:
            The folder the steps write into (:attr:`build`): the output, or with --overwrite over
            existing entries of ours, the staging folder beside it.

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
        self._clean_leftovers()
        present = self._present(self.output) if self.output.is_dir() else []
        if self.overwrite:
            if present:
                self.build = self.staging
                self.build.mkdir(parents=True)
                CONSOLE.print(f"[cyan]--overwrite[/]: building in {self.build}; the scene in {self.output} is replaced "
                              "only when this run succeeds")
            self.output.mkdir(parents=True, exist_ok=True)
            return self.build
        if self.record_path.is_file():
            record = json.loads(self.record_path.read_text())
            if record.get("version") != STEP_RECORD_VERSION:
                raise FileExistsError(
                    f"{self.record_path}: step record of version {record.get('version')} (this is {STEP_RECORD_VERSION}); "
                    "pass --overwrite to process again (the current scene stays until the new one is complete)"
                )
            self._record = record
        else:
            leftovers = [n for n in present if n in self.scratch]
            if leftovers:
                CONSOLE.print(f"[yellow]note[/]: removing {', '.join(leftovers)} in {self.output}, left by an interrupted "
                              "run before its first step finished")
                self.clear(leftovers)
            others = sorted(p.name for p in self.output.iterdir()) if self.output.is_dir() else []
            if others:
                shown = ", ".join(others[:5]) + (" ..." if len(others) > 5 else "")
                raise FileExistsError(
                    f"{self.output}: folder exists and holds files edygs-process did not write ({shown}); "
                    "choose another output folder or pass --overwrite (which replaces only edygs-process's own entries)"
                )
        self.output.mkdir(parents=True, exist_ok=True)
        return self.build

    def _clean_leftovers(self) -> None:
        """Remove the staging folder of an interrupted --overwrite run; finish or undo an interrupted swap."""
        if self.retired.is_dir():
            if not (self.output / STEP_RECORD_NAME).is_file():  # the swap stopped before the new scene moved in
                for name in self._present(self.retired):
                    if not (self.output / name).exists():
                        os.replace(self.retired / name, self.output / name)
                CONSOLE.print(f"[yellow]note[/]: put back the previous scene from {self.retired} (an interrupted --overwrite swap)")
            shutil.rmtree(self.retired)
        if self.staging.is_dir():
            CONSOLE.print(f"[yellow]note[/]: removing {self.staging}, the unfinished build of an interrupted --overwrite run")
            shutil.rmtree(self.staging)

    def commit(self) -> None:
        """After a successful run: swap the staged entries into the output (no-op when built in place)."""
        if self.build == self.output:
            return
        self.retired.mkdir()
        for name in self._present(self.output):
            os.replace(self.output / name, self.retired / name)
        for name in self._present(self.staging):
            os.replace(self.staging / name, self.output / name)
        shutil.rmtree(self.staging)
        shutil.rmtree(self.retired)
        self.build = self.output
        CONSOLE.print(f"[bold green]✓[/] replaced the previous scene in {self.output}")

    def abandon(self) -> None:
        """After a failed run: drop the staging folder; the output is as it was (no-op when built in place)."""
        if self.build != self.output and self.staging.is_dir():
            shutil.rmtree(self.staging)
            CONSOLE.print(f"[yellow]note[/]: the previous scene in {self.output} is unchanged (this run failed)")
        self.build = self.output

    def clear(self, names: Optional[Sequence[str]] = None) -> None:
        """Remove the owned entries (or the given subset of them) from the build folder."""
        for name in self.owned if names is None else names:
            path = self.build / name
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
            if self.finished(self.final_step) is not None:
                raise FileExistsError(
                    f"{self.output}: step '{name}' was finished with other inputs or settings, and the processed scene "
                    "there was made from them. Pass --overwrite to process again (the current scene stays until the new "
                    "one is complete), or choose another output folder"
                )
            CONSOLE.print(f"[yellow]↻ {name}[/]: finished earlier with other inputs or settings; redoing it and the steps "
                          "after it (no processed scene there yet)")
            steps = list(self._record["steps"])
            for later in steps[steps.index(name):]:
                del self._record["steps"][later]
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
