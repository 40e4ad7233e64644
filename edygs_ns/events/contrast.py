"""The event contrast threshold Θ (per polarity: Θ+ and Θ−) from blurry frames and their events.

Model (the one EDI rests on): the latent log intensity moves by +Θ+ per positive and −Θ− per
negative event, L(t) = L(t_0) exp(Θ+ P(t) − Θ− N(t)) with P, N the pixel's positive and negative
event counts since t_0, and a blurry frame is the mean of L over its exposure. For two
consecutive exposures p and q = p + 1, with t_0 the start of p and M instants τ spread evenly over
each exposure (ends included), the unknown L(t_0) cancels:

    log B_q − log B_p = LSE_m(Θ+ P(τ^q_m) − Θ− N(τ^q_m)) − LSE_m(Θ+ P(τ^p_m) − Θ− N(τ^p_m))

(LSE = log-sum-exp; the 1/M of the means cancels; B is the grey level plus LOG_EPS). It is exact
up to the M-point quadrature of the exposure integral, needs no motion model, and uses every event
from p's start to q's end. Each usable pixel of each consecutive pair gives one equation: grey
level well inside the 8-bit range in both frames, and at least MIN_NET_EVENTS net events between
the two exposures. Θ+ and Θ− (and the single Θ, Θ+ = Θ−, that EDI uses) are the robust (Huber,
scale from the MAD) Gauss-Newton least squares of the log-ratio residuals. The spread reported
is the standard deviation of Θ fitted to each frame pair alone (how stable Θ is over the clip).

Choices, measured on edygs-synth captures (64x48x6 and 128x96x12, Θ = 0.15, 0.2, 0.3, per-pixel
threshold σ = 0 and 0.1 Θ): the residuals are dominated by the counts' quantisation (up to one
threshold at each end, ~0.45 Θ rms). Fitting counts to log ratios the other way round (residuals
in events) overestimates Θ by 7-28%; fitting log ratios to counts over every pixel with events
underestimates it by up to 5%, 8% under threshold noise (small counts are quantised coarsely;
pixels with lower thresholds fire more and weigh more). Keeping pixels with at least 2 net events
leaves errors of −0.3..+1.5% without and −1.6..−5.5% with threshold noise. The quadrature
matters: edygs-synth averages 9 sub-frames (ends included), which M = 9 matches; on a capture of
5 sub-frames, M = 17 instead of 5 moved Θ by −7%. A real exposure is continuous: there, a larger
M is closer.

Memory stays bounded: :class:`ContrastAccumulator` takes one exposure's counts at a time (binned
from the read the caller makes anyway for EDI, chunk by chunk: :mod:`edygs_ns.events.stream`) and
keeps at most ``max_pixels`` equations in all.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Dict, List, Literal, Optional, Sequence, Tuple, Union

import numpy as np

from edygs_ns.events.accumulate import bin_chunks, bin_events, polarity_events
from edygs_ns.events.exposures import Exposure
from edygs_ns.events.readers import ArrayEventSource, EventSource
from edygs_ns.events.types import EventArray

#: Θ for EDI when it is neither given nor estimable (pre-binned events hold none between
#: exposures): a common DAVIS setting, the one E2NeRF's synthetic data and EvDeblurNeRF's Blender
#: scenes use.
FALLBACK_THETA = 0.2
#: Grey level of linear RGB frames (ITU-R BT.601 luma weights, as the event simulator uses).
GREY_WEIGHTS = (0.299, 0.587, 0.114)
#: Offset inside the log, log(B + LOG_EPS), as in the event simulator (keeps black pixels finite).
LOG_EPS = 1e-3
#: Usable pixels have every channel of both frames within [MIN_LEVEL, MAX_LEVEL] (linear, 0..1):
#: darker pixels drown in 8-bit quantisation, brighter ones may be clipped.
MIN_LEVEL = 0.05
MAX_LEVEL = 0.95
#: Usable pixels have at least this many net events between the two exposures (mean over their
#: instants): the count's quantisation (up to one event at each end) then biases the fit little.
MIN_NET_EVENTS = 2.0
#: Instants per exposure of the quadrature of the exposure integral (ends included).
SAMPLES_PER_EXPOSURE = 9
#: Most equations (pixel x frame pair) kept in all; equally shared among frame pairs.
MAX_PIXELS = 200_000
#: Fewest equations kept per frame pair when MAX_PIXELS is shared among many pairs.
MIN_PIXELS_PER_PAIR = 256
#: Fewest usable equations for an estimate (fewer: no estimate).
MIN_PIXELS = 200
#: Fewest usable equations of one frame pair for its own fit (the spread).
MIN_PIXELS_PAIR_FIT = 50
#: Gauss-Newton start and bounds of any threshold.
THETA_START = 0.2
THETA_BOUNDS = (0.01, 2.0)
#: Gauss-Newton iterations (each reweights) and the relative step below which it stops.
MAX_ITERATIONS = 30
STEP_TOLERANCE = 1e-5
#: Huber's constant, in units of the residual scale (95% efficiency under Gaussian noise).
HUBER_K = 1.345
#: MAD to standard deviation under Gaussian noise.
MAD_TO_SIGMA = 1.4826
#: Smallest residual scale (log units), so that a perfect fit does not divide by zero.
MIN_SCALE = 1e-6
#: Seed of the per-pair pixel subsampling (the estimate is repeatable).
SUBSAMPLE_SEED = 0


@dataclass
class ContrastEstimate:
    """The contrast thresholds fitted to a clip.

    Attributes:
        theta: the single threshold (Θ+ = Θ−) that EDI uses.
        theta_pos: Θ+, log-intensity rise per positive event.
        theta_neg: Θ−, log-intensity fall per negative event.
        spread: standard deviation of Θ fitted to each frame pair alone (0 with one pair).
        n_pixels: equations (pixel x frame pair) used.
        n_pairs: consecutive frame pairs used.
        residual_scale: robust standard deviation of the log-ratio residuals at ``theta``.
    """

    theta: float
    theta_pos: float
    theta_neg: float
    spread: float
    n_pixels: int
    n_pairs: int
    residual_scale: float

    def to_dict(self) -> Dict[str, Any]:
        return asdict(self)

    def summary(self) -> str:
        """One line: Θ, Θ+ / Θ−, spread and what it was fitted to."""
        return (f"Θ = {self.theta:.3f} (Θ+ {self.theta_pos:.3f}, Θ− {self.theta_neg:.3f}, spread over frame pairs "
                f"±{self.spread:.3f}) from {self.n_pixels:,} pixels of {self.n_pairs} frame pairs")


def sample_times_us(exposure: Exposure, m: int = SAMPLES_PER_EXPOSURE) -> np.ndarray:
    """[m] int64 instants evenly spread over an exposure, its start and end included."""
    return np.round(np.linspace(exposure.start_us, exposure.end_us, m)).astype(np.int64)


def grey_level(frame: np.ndarray) -> np.ndarray:
    """[H, W] float64 grey of a [H, W] or [H, W, C] linear frame in [0, 1] (C = 3: luma weights)."""
    frame = np.asarray(frame, dtype=np.float64)
    if frame.ndim == 2:
        return frame
    if frame.ndim == 3 and frame.shape[2] == len(GREY_WEIGHTS):
        return frame @ np.asarray(GREY_WEIGHTS)
    if frame.ndim == 3 and frame.shape[2] == 1:
        return frame[..., 0]
    raise ValueError(f"grey_level: frame must be [H, W], [H, W, 1] or [H, W, 3], got shape {frame.shape}")


def _well_exposed(frame: np.ndarray) -> np.ndarray:
    """[H, W] bool: every channel within [MIN_LEVEL, MAX_LEVEL]."""
    frame = np.asarray(frame)
    inside = (frame >= MIN_LEVEL) & (frame <= MAX_LEVEL)
    return inside if inside.ndim == 2 else inside.all(axis=-1)


def _cumulative_counts(events: EventArray, edges: np.ndarray, polarity: int) -> np.ndarray:
    """[len(edges), H, W] float32 count of events of one polarity from edges[0] to each edge."""
    return _cumulative(bin_events(polarity_events(events, polarity), edges))


def _cumulative(bins: np.ndarray) -> np.ndarray:
    """[B + 1, H, W] float32 running sums of [B, H, W] bins, zero first."""
    out = np.zeros((len(bins) + 1,) + bins.shape[1:], np.float32)
    np.cumsum(bins, axis=0, out=out[1:])
    return out


class ContrastAccumulator:
    """Collects the equations of consecutive exposures, one exposure at a time; then fits Θ.

    Args:
        n_exposures: exposures that will be added (shares MAX_PIXELS among the pairs).
        max_pixels: most equations kept in all.
        samples: instants per exposure of the exposure integral.
    """

    def __init__(self, n_exposures: int, max_pixels: int = MAX_PIXELS, samples: int = SAMPLES_PER_EXPOSURE) -> None:
        self.per_pair = max(MIN_PIXELS_PER_PAIR, max_pixels // max(n_exposures - 1, 1))
        self.samples = samples
        self.rng = np.random.default_rng(SUBSAMPLE_SEED)
        self._previous: Optional[Dict[str, Any]] = None
        self._parts: List[Dict[str, np.ndarray]] = []
        self._pairs = 0

    def add(self, frame: np.ndarray, exposure: Exposure, events: EventArray, next_start_us: Optional[int],
            count_scale: float = 1.0) -> None:
        """Add one exposure (in time order).

        Args:
            frame: [H, W, 3] or [H, W] linear blurry frame in [0, 1].
            exposure: its exposure (µs on the event clock).
            events: the events from its start to ``next_start_us`` at least (more are ignored).
            next_start_us: start of the next exposure, or None for the last one.
            count_scale: factor on the event counts (1 / downscale², as for the EDI bins).

        Raises:
            ValueError: the frame's size is not the events' sensor size.
        """
        self._check_frame(frame, exposure, events.sensor_size)
        edges = self.edges(exposure, next_start_us)
        if edges is None:  # an exposure of fewer µs than instants: no equations
            self._previous = None
            return
        self.add_binned(frame, exposure, bin_events(polarity_events(events, +1), edges),
                        bin_events(polarity_events(events, -1), edges), count_scale)

    @staticmethod
    def _check_frame(frame: np.ndarray, exposure: Exposure, sensor_size: Tuple[int, int]) -> None:
        if np.asarray(frame).shape[:2] != tuple(sensor_size):
            raise ValueError(f"ContrastAccumulator.add: frame {np.asarray(frame).shape} does not match the events' "
                             f"sensor {tuple(sensor_size)} (frame {exposure.frame})")

    def edges(self, exposure: Exposure, next_start_us: Optional[int]) -> Optional[np.ndarray]:
        """The bin edges of one exposure's counts: its instants, then the next start when later; None: too short."""
        times = sample_times_us(exposure, self.samples)
        if np.any(np.diff(times) <= 0):
            return None
        reaches_next = next_start_us is not None and next_start_us > times[-1]
        return np.append(times, next_start_us) if reaches_next else times

    def skip(self, frame: np.ndarray, exposure: Exposure, sensor_size: Tuple[int, int]) -> None:
        """An exposure with no edges (:meth:`edges` is None): it breaks the chain of pairs."""
        self._check_frame(frame, exposure, sensor_size)
        self._previous = None

    def add_binned(self, frame: np.ndarray, exposure: Exposure, pos_bins: np.ndarray, neg_bins: np.ndarray,
                   count_scale: float = 1.0) -> None:
        """Add one exposure (in time order) from its counts binned at :meth:`edges`.

        Args:
            frame: [H, W, 3] or [H, W] linear blurry frame in [0, 1].
            exposure: its exposure.
            pos_bins, neg_bins: [len(edges) - 1, H, W] counts of the positive / negative events
                (each +1) between consecutive edges (:func:`edygs_ns.events.accumulate.bin_chunks`).
            count_scale: factor on the counts.
        """
        self._check_frame(frame, exposure, pos_bins.shape[1:])
        current = {
            "log": np.log(grey_level(frame) + LOG_EPS),
            "ok": _well_exposed(frame),
            "pos": _cumulative(pos_bins) * count_scale,
            "neg": _cumulative(neg_bins) * count_scale,
            "reaches_next": len(pos_bins) == self.samples,  # samples instants + the next start
        }
        if self._previous is not None and self._previous["reaches_next"]:
            self._add_pair(self._previous, current)
        self._previous = current

    def _add_pair(self, p: Dict[str, Any], q: Dict[str, Any]) -> None:
        m = self.samples
        gap_pos, gap_neg = p["pos"][m], p["neg"][m]  # counts from p's start to q's start
        net_p = (p["pos"][:m] - p["neg"][:m]).mean(axis=0)
        net_q = (q["pos"][:m] - q["neg"][:m]).mean(axis=0) + gap_pos - gap_neg
        moved = np.abs(net_q - net_p) >= MIN_NET_EVENTS
        pixels = np.flatnonzero((p["ok"] & q["ok"] & moved).reshape(-1))
        if len(pixels) > self.per_pair:
            pixels = np.sort(self.rng.choice(pixels, self.per_pair, replace=False))
        if len(pixels) == 0:
            return

        def flat(maps: np.ndarray) -> np.ndarray:  # [m, H, W] -> [S, m] at the chosen pixels
            return maps.reshape(maps.shape[0], -1)[:, pixels].T

        self._parts.append({
            "y": (q["log"] - p["log"]).reshape(-1)[pixels],
            "pos_p": flat(p["pos"][:m]), "neg_p": flat(p["neg"][:m]),
            "pos_q": flat(q["pos"][:m] + gap_pos), "neg_q": flat(q["neg"][:m] + gap_neg),
            "pair": np.full(len(pixels), self._pairs, np.int64),
        })
        self._pairs += 1

    @property
    def n_equations(self) -> int:
        return int(sum(len(part["y"]) for part in self._parts))

    def estimate(self) -> Optional[ContrastEstimate]:
        """The fit over every pair added, or None with fewer than MIN_PIXELS usable equations (see reason)."""
        if self.n_equations < MIN_PIXELS:
            return None
        data = {key: np.concatenate([part[key] for part in self._parts]) for key in self._parts[0]}
        return fit_contrast(**data)

    def reason(self) -> str:
        """Why estimate() gives None ("" when it does not)."""
        if self.n_equations >= MIN_PIXELS:
            return ""
        return (f"{self.n_equations} usable pixels in {self._pairs} consecutive frame pairs, fewer than {MIN_PIXELS}: "
                f"too little motion, or frames too dark or bright (usable: grey in [{MIN_LEVEL}, {MAX_LEVEL}] and at "
                f"least {MIN_NET_EVENTS:g} net events between the frames)")


def _lse_and_mean(pos: np.ndarray, neg: np.ndarray, a: np.ndarray, b: np.ndarray):
    """Per row of [S, m]: log-sum-exp of a P − b N, and the softmax means of P and N (a, b: [1, 1] or [S, 1])."""
    z = a * pos - b * neg
    top = z.max(axis=1, keepdims=True)
    w = np.exp(z - top)
    total = w.sum(axis=1, keepdims=True)
    w /= total
    return (top + np.log(total))[:, 0], (w * pos).sum(axis=1), (w * neg).sum(axis=1)


def _model(data: Dict[str, np.ndarray], a: Any, b: Any):
    """Residuals (model − observed log ratio) [S] and their derivatives in Θ+ and Θ−.

    a, b: Θ+ and Θ−, scalars or one per equation ([S]).
    """
    a = np.reshape(np.asarray(a, np.float64), (-1, 1))
    b = np.reshape(np.asarray(b, np.float64), (-1, 1))
    lq, pq, nq = _lse_and_mean(data["pos_q"], data["neg_q"], a, b)
    lp, pp, np_ = _lse_and_mean(data["pos_p"], data["neg_p"], a, b)
    return lq - lp - data["y"], pq - pp, -(nq - np_)


def _robust_scale(residuals: np.ndarray) -> float:
    return max(MAD_TO_SIGMA * float(np.median(np.abs(residuals - np.median(residuals)))), MIN_SCALE)


def _huber_weights(residuals: np.ndarray, scale: float) -> np.ndarray:
    limit = HUBER_K * scale
    return np.minimum(1.0, limit / np.maximum(np.abs(residuals), MIN_SCALE))


def _gauss_newton(data: Dict[str, np.ndarray], tied: bool) -> np.ndarray:
    """Robust fit of (Θ+, Θ−), or of one Θ when tied; returns [2] (equal entries when tied)."""
    theta = np.array([THETA_START, THETA_START])
    for _ in range(MAX_ITERATIONS):
        r, ga, gb = _model(data, theta[0], theta[1])
        w = _huber_weights(r, _robust_scale(r))
        if tied:
            g = ga + gb
            step = -np.sum(w * g * r) / max(np.sum(w * g * g), MIN_SCALE)
            step = np.array([step, step])
        else:
            jac = np.stack([ga, gb], axis=1)
            normal = jac.T @ (w[:, None] * jac)
            step = -np.linalg.lstsq(normal, jac.T @ (w * r), rcond=None)[0]
        new = np.clip(theta + step, *THETA_BOUNDS)
        done = np.all(np.abs(new - theta) <= STEP_TOLERANCE * np.maximum(theta, THETA_BOUNDS[0]))
        theta = new
        if done:
            break
    return theta


def _pair_spread(data: Dict[str, np.ndarray], theta: float) -> float:
    """Std of Θ fitted to each pair alone (robust Gauss-Newton from the joint fit, all pairs at once)."""
    pairs = data["pair"]
    n_pairs = int(pairs.max()) + 1
    counts = np.bincount(pairs, minlength=n_pairs)
    per_pair = np.full(n_pairs, theta)
    for _ in range(MAX_ITERATIONS):
        t = per_pair[pairs]
        r, ga, gb = _model(data, t, t)
        g = ga + gb
        w = _huber_weights(r, _robust_scale(r))
        num = np.bincount(pairs, weights=w * g * r, minlength=n_pairs)
        den = np.bincount(pairs, weights=w * g * g, minlength=n_pairs)
        new = np.clip(per_pair - num / np.maximum(den, MIN_SCALE), *THETA_BOUNDS)
        done = np.all(np.abs(new - per_pair) <= STEP_TOLERANCE * per_pair)
        per_pair = new
        if done:
            break
    usable = per_pair[counts >= MIN_PIXELS_PAIR_FIT]
    return float(np.std(usable)) if len(usable) > 1 else 0.0


def fit_contrast(y: np.ndarray, pos_p: np.ndarray, neg_p: np.ndarray, pos_q: np.ndarray, neg_q: np.ndarray,
                 pair: np.ndarray) -> ContrastEstimate:
    """Robust least squares of the log-ratio equations (module docstring).

    Args:
        y: [S] log(B_q + eps) − log(B_p + eps) per equation.
        pos_p, neg_p: [S, m] positive / negative counts from p's start to each instant of p.
        pos_q, neg_q: [S, m] the same from p's start to each instant of q.
        pair: [S] frame-pair index of each equation (for the spread).

    Returns:
        The estimate.

    Raises:
        ValueError: the arrays' shapes disagree.
    """
    s = len(y)
    for name, value in (("pos_p", pos_p), ("neg_p", neg_p), ("pos_q", pos_q), ("neg_q", neg_q)):
        if value.ndim != 2 or value.shape[0] != s:
            raise ValueError(f"fit_contrast: {name} must be [S={s}, m], got shape {value.shape}")
    if pair.shape != (s,):
        raise ValueError(f"fit_contrast: pair must be [S={s}], got shape {pair.shape}")
    data = {"y": np.asarray(y, np.float64), "pos_p": pos_p.astype(np.float64), "neg_p": neg_p.astype(np.float64),
            "pos_q": pos_q.astype(np.float64), "neg_q": neg_q.astype(np.float64), "pair": pair}
    theta = float(_gauss_newton(data, tied=True)[0])
    theta_pos, theta_neg = (float(v) for v in _gauss_newton(data, tied=False))
    residuals = _model(data, theta, theta)[0]
    return ContrastEstimate(
        theta=theta, theta_pos=theta_pos, theta_neg=theta_neg, spread=_pair_spread(data, theta),
        n_pixels=s, n_pairs=len(np.unique(pair)), residual_scale=_robust_scale(residuals),
    )


def read_span_us(exposures: Sequence[Exposure], i: int) -> Tuple[int, int]:
    """The event window exposure i needs: its start to the later of its end and the next start."""
    start, end = int(exposures[i].start_us), int(exposures[i].end_us)
    if i + 1 < len(exposures):
        end = max(end, int(exposures[i + 1].start_us))
    return start, end


def next_start_us(exposures: Sequence[Exposure], i: int) -> Optional[int]:
    """Start of exposure i + 1, or None after the last one."""
    return int(exposures[i + 1].start_us) if i + 1 < len(exposures) else None


def estimate_contrast(
    frames: Sequence[np.ndarray], exposures: Sequence[Exposure], events: Union[EventSource, EventArray],
    count_scale: float = 1.0,
) -> Optional[ContrastEstimate]:
    """Θ, Θ+ and Θ− of a clip, reading each exposure's events once.

    Args:
        frames: n [H, W, 3] or [H, W] linear blurry frames in [0, 1], in time order.
        exposures: their n exposures (µs on the event clock).
        events: the events (an EventSource reads only the windows needed).
        count_scale: factor on the event counts (1 / downscale²).

    Returns:
        The estimate, or None with too few usable pixels.

    Raises:
        ValueError: frames and exposures differ in number.
    """
    if len(frames) != len(exposures):
        raise ValueError(f"estimate_contrast: {len(frames)} frames but {len(exposures)} exposures")
    source = ArrayEventSource(events) if isinstance(events, EventArray) else events
    accumulator = ContrastAccumulator(len(exposures))
    for i, (frame, exposure) in enumerate(zip(frames, exposures)):  # one chunked read per exposure
        edges = accumulator.edges(exposure, next_start_us(exposures, i))
        if edges is None:
            accumulator.skip(frame, exposure, source.sensor_size)
            continue
        (pos, neg), _ = bin_chunks(source.chunks(*read_span_us(exposures, i)), [(edges, +1), (edges, -1)],
                                   source.sensor_size)
        accumulator.add_binned(frame, exposure, pos, neg, count_scale)
    return accumulator.estimate()


@dataclass
class ThetaChoice:
    """The Θ that EDI uses, where it came from, and the estimate (reported even when not used).

    Attributes:
        theta: the threshold EDI uses.
        source: "estimated", "given" (--theta) or "fallback" (no estimate: the input layout's
            default, e.g. E2NeRF real data's 0.3, else FALLBACK_THETA).
        estimate: the fit, or None when there was none.
        reason: why there is no estimate ("" when there is one).
        fallback_origin: where a fallback Θ comes from ("" for FALLBACK_THETA).
    """

    theta: float
    source: Literal["estimated", "given", "fallback"]
    estimate: Optional[ContrastEstimate]
    reason: str = ""
    fallback_origin: str = ""

    def line(self) -> str:
        """The one log line: the estimate, and which Θ EDI uses."""
        found = self.estimate.summary() if self.estimate is not None else f"not estimated ({self.reason})"
        use = {"estimated": "EDI uses the estimate", "given": f"EDI uses --theta {self.theta:g} as given",
               "fallback": f"EDI uses Θ = {self.theta:g}"
               + (f" ({self.fallback_origin})" if self.fallback_origin else "") + "; pass --theta to set it"}[self.source]
        return f"contrast threshold: {found}; {use}"

    def to_dict(self) -> Dict[str, Any]:
        return {"theta": self.theta, "source": self.source, "reason": self.reason,
                "estimate": self.estimate.to_dict() if self.estimate is not None else None,
                "fallback_origin": self.fallback_origin}

    @classmethod
    def from_dict(cls, data: Dict[str, Any]) -> "ThetaChoice":
        estimate = ContrastEstimate(**data["estimate"]) if data.get("estimate") else None
        return cls(float(data["theta"]), data["source"], estimate, data.get("reason", ""),
                   data.get("fallback_origin", ""))


def choose_theta(
    estimate: Optional[ContrastEstimate],
    given: Optional[float],
    reason: str = "",
    fallback: Optional[float] = None,
    fallback_origin: str = "",
) -> ThetaChoice:
    """The given Θ if any, else the estimate, else the input layout's default, else FALLBACK_THETA.

    A layout's default (the authors' value, e.g. 0.3 for E2NeRF real data) applies only where
    neither --theta nor an estimate from the data exists: both describe this capture better.

    Args:
        estimate: the fit from frames and events, or None.
        given: --theta, or None.
        reason: why there is no estimate.
        fallback: the input layout's default Θ, or None for FALLBACK_THETA.
        fallback_origin: where ``fallback`` comes from, quoted in the log line.

    Raises:
        ValueError: the given Θ is not positive.
    """
    if given is not None:
        if not given > 0:
            raise ValueError(f"--theta must be positive, got {given}")
        return ThetaChoice(float(given), "given", estimate, reason)
    if estimate is not None:
        return ThetaChoice(estimate.theta, "estimated", estimate)
    if fallback is not None:
        return ThetaChoice(float(fallback), "fallback", None, reason, fallback_origin)
    return ThetaChoice(FALLBACK_THETA, "fallback", None, reason)
