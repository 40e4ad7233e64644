"""Which exposures the events cover, and what to do with those they do not.

An exposure is covered when the events span it: first event <= exposure start and exposure
end <= last event. Events are discrete, so a short quiet moment at the edge of the recording is
no gap; a longer overhang means a piece of the first (or last) event bin is missing, and the EDI
latents of that frame would be wrong without a word. So, per exposure, the overhang (the part of
the exposure outside [first event, last event]) is compared with its event bin:

- at most :data:`QUIET_EDGE_EVENT_INTERVALS` mean inter-event intervals (and within the next
  tolerance): covered;
- up to :data:`PARTIAL_BIN_TOLERANCE` of a bin: kept, and reported as partial coverage;
- more: not covered. Such frames sit at the ends of the selection (events are one span). They
  are dropped with a one-line notice when they are few (at most :data:`MAX_DROP_FRACTION` of
  the frames: a recording that starts or stops a moment early, like a DAVIS whose first APS
  exposure begins before the first event); otherwise the clocks probably disagree and the
  exposures are refused with the options that fix it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import List, Sequence, Tuple

from edygs_ns.events.exposures import Exposure

#: An edge overhang shorter than this many mean inter-event intervals is a quiet instant.
QUIET_EDGE_EVENT_INTERVALS = 20.0
#: An overhang up to this fraction of one event bin keeps the frame (reported as partial).
PARTIAL_BIN_TOLERANCE = 0.25
#: Uncovered frames are dropped (with a notice) when at most this fraction of the frames.
MAX_DROP_FRACTION = 0.25
#: Frames named in one notice at most.
MAX_NAMED_FRAMES = 8
#: What a refusal suggests about the clocks by default.
CLOCK_HINT = "check the event file and the exposure times"


@dataclass
class Coverage:
    """How the events cover a list of exposures.

    Attributes:
        t_first, t_last: first and last event, µs.
        kept: positions (into the exposure list) of the frames kept.
        dropped: positions of the frames the events do not cover.
        partial: (position, overhang µs, fraction of a bin) of kept frames with a small overhang.
    """

    t_first: int
    t_last: int
    kept: List[int] = field(default_factory=list)
    dropped: List[int] = field(default_factory=list)
    partial: List[Tuple[int, int, float]] = field(default_factory=list)


def overhang_us(exposure: Exposure, t_first: int, t_last: int) -> int:
    """µs of the exposure outside [t_first, t_last] (before the first plus after the last event)."""
    before = max(0, min(t_first, exposure.end_us) - exposure.start_us)
    after = max(0, exposure.end_us - max(t_last, exposure.start_us))
    return int(before + after)


def measure_coverage(t_first: int, t_last: int, n_events: int, exposures: Sequence[Exposure], k: int) -> Coverage:
    """Sort exposures into covered, partially covered (kept) and not covered (see the module doc).

    Args:
        t_first, t_last: first and last event timestamp, µs.
        n_events: number of events (sets the mean inter-event interval).
        exposures: the exposures, µs on the event clock.
        k: latents per exposure (an exposure has k - 1 event bins).
    """
    quiet = QUIET_EDGE_EVENT_INTERVALS * (t_last - t_first) / max(n_events - 1, 1)
    coverage = Coverage(int(t_first), int(t_last))
    for i, exposure in enumerate(exposures):
        gap = overhang_us(exposure, t_first, t_last)
        bin_us = (exposure.end_us - exposure.start_us) / (k - 1)
        if gap <= min(quiet, PARTIAL_BIN_TOLERANCE * bin_us):
            coverage.kept.append(i)
        elif gap <= PARTIAL_BIN_TOLERANCE * bin_us:
            coverage.kept.append(i)
            coverage.partial.append((i, gap, gap / bin_us))
        else:
            coverage.dropped.append(i)
    return coverage


def _frame_list(positions: Sequence[int], exposures: Sequence[Exposure], names: Sequence[str]) -> str:
    shown = [f"frame {exposures[i].frame} ({names[i]})" for i in positions[:MAX_NAMED_FRAMES]]
    more = len(positions) - len(shown)
    return ", ".join(shown) + (f" and {more} more" if more > 0 else "")


def _selection_option(kept: Sequence[int], selected: Sequence[int]) -> str:
    """The --frame-start/--frame-end options that keep exactly the covered frames (input-list indices)."""
    return f"--frame-start {selected[kept[0]]} --frame-end {selected[kept[-1]] + 1}"


def resolve_coverage(
    coverage: Coverage,
    exposures: Sequence[Exposure],
    names: Sequence[str],
    selected: Sequence[int],
    source: str,
    hint: str = CLOCK_HINT,
    allow_drop: bool = True,
) -> List[str]:
    """Accept a coverage (returning its notices) or raise ValueError with the options that fix it.

    Args:
        coverage: from :func:`measure_coverage`.
        exposures, names: the exposures and their frames' names (for the messages).
        selected: each exposure's index in the input's frame list (for --frame-start/--frame-end).
        source: the event file, named in every line.
        hint: what to check about the clocks (time unit, offset) when refusing.
        allow_drop: drop a few uncovered edge frames; False refuses any.

    Returns:
        One-line notices: the dropped frames, and the partially covered ones.

    Raises:
        ValueError: too many frames (or, without allow_drop, any) are not covered.
    """
    span = f"events cover [{coverage.t_first}, {coverage.t_last}] µs"
    n = len(exposures)
    if coverage.dropped:
        first = exposures[coverage.dropped[0]]
        detail = (f"{source}: {span} but frame {first.frame} ({names[coverage.dropped[0]]}) is exposed over "
                  f"[{first.start_us}, {first.end_us}] µs")
        if not coverage.kept:
            raise ValueError(f"{detail}, and so is every other frame: no frame is covered; {hint}")
        if not allow_drop or len(coverage.dropped) > MAX_DROP_FRACTION * n:
            option = _selection_option(coverage.kept, selected)
            raise ValueError(
                f"{detail} ({len(coverage.dropped)} of {n} frames not covered); pass {option} to use only the "
                f"covered frames, or {hint}"
            )
    notes = []
    if coverage.dropped:
        notes.append(
            f"{source}: dropped {len(coverage.dropped)} of {n} frames whose exposure the events do not cover ({span}): "
            f"{_frame_list(coverage.dropped, exposures, names)}"
        )
    if coverage.partial:
        parts = ", ".join(f"frame {exposures[i].frame} ({gap} µs, {fraction:.0%} of a bin)"
                          for i, gap, fraction in coverage.partial[:MAX_NAMED_FRAMES])
        more = len(coverage.partial) - min(len(coverage.partial), MAX_NAMED_FRAMES)
        notes.append(
            f"{source}: {len(coverage.partial)} kept frame(s) reach slightly outside the events ({span}), their edge bin "
            f"partly without events: {parts}" + (f" and {more} more" if more > 0 else "")
        )
    return notes
