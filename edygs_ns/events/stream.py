"""One exposure's event bins for EDI and its Θ equations, from one chunked read of its events.

``edygs-process`` reads each exposure's events once, from its start to the next exposure's start
(:func:`edygs_ns.events.contrast.read_span_us`), and bins them twice: between its k latent times
(the EDI event maps) and, per polarity, between the instants of the Θ fit
(:class:`edygs_ns.events.contrast.ContrastAccumulator`). The read goes through
:meth:`edygs_ns.events.readers.EventSource.chunks`, so at most ``max_events`` events (plus the
[bins, H, W] sums) are in memory at once, however many events the file or the window holds; the
bins equal those of the whole window read at once (see :func:`edygs_ns.events.accumulate.bin_chunks`).
"""

from __future__ import annotations

from typing import Optional, Sequence

import numpy as np

from edygs_ns.events.accumulate import bin_chunks, empty_window_error, latent_times_us
from edygs_ns.events.contrast import ContrastAccumulator, next_start_us, read_span_us
from edygs_ns.events.exposures import Exposure
from edygs_ns.events.readers import READ_CHUNK_EVENTS, EventSource


def bin_exposure(
    source: EventSource,
    exposures: Sequence[Exposure],
    i: int,
    k: int,
    count_scale: float = 1.0,
    contrast: Optional[ContrastAccumulator] = None,
    frame: Optional[np.ndarray] = None,
    max_events: int = READ_CHUNK_EVENTS,
) -> np.ndarray:
    """The EDI event bins of exposure i, and (with ``contrast``) its Θ equations, from one chunked read.

    Args:
        source: the events.
        exposures: the n exposures, in time order (the next one bounds the read).
        i: which exposure.
        k: latent frames per exposure (k - 1 bins).
        count_scale: factor on the counts (1 / downscale²).
        contrast: the accumulator of the Θ fit, fed this exposure (in time order); None: no Θ.
        frame: the exposure's linear blurry frame [H, W, 3] in [0, 1] (needed with ``contrast``).
        max_events: most events read at once (<= 0: the whole window at once).

    Returns:
        [k-1, H, W] float32 signed counts between consecutive latent times, times ``count_scale``.

    Raises:
        ValueError: no event between the exposure's first and last latent time (names the frame),
            a bad chunk of the file (names the file and the event index), or a frame whose size
            is not the sensor's.
    """
    exposure = exposures[i]
    times = latent_times_us(exposure.start_us, exposure.end_us, k)
    requests = [(times, None)]
    edges = None
    if contrast is not None:
        if frame is None:
            raise ValueError("bin_exposure: the Θ fit (contrast) needs the exposure's frame")
        edges = contrast.edges(exposure, next_start_us(exposures, i))
        if edges is not None:
            requests += [(edges, +1), (edges, -1)]
    bins, counts = bin_chunks(source.chunks(*read_span_us(exposures, i), max_events), requests, source.sensor_size)
    if counts[0] == 0:
        raise empty_window_error(source, exposure)
    if contrast is not None:
        if edges is None:
            contrast.skip(frame, exposure, source.sensor_size)
        else:
            contrast.add_binned(frame, exposure, bins[1], bins[2], count_scale)
    return bins[0] * count_scale
