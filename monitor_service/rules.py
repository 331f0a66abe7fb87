"""Alert rules whose false-alarm guarantee covers the alerts actually raised, as pure functions.

An alert rule turns an episode's scored decisions (NMSE in decision-step order) into a *running statistic*
r_1, r_2, ... and raises an alert when ``debounce`` consecutive values exceed the threshold (``alerts.step_alert``).
Two rules:

- ``running``: r_i = median of the last ``window`` NMSE values (fewer at the start of the episode).
- ``band``: each NMSE is first judged against the successful episodes *at the same decision step*
  (time-varying band, as in FAIL-Detect): z = (log NMSE - m(step)) / s(step), with m and s the median and the
  MAD-scale of log NMSE of calibration successes at that step; r_i = median of the last ``window`` z values.

Guarantee per episode length. The statistic is judged against a threshold that depends on the decision index i
(the position among the episode's scored decisions): T(i) = q(i) + lambda (``band``) or q(i) x exp(lambda)
(``running``, a ratio on NMSE), where the *shape* q(i) is the median, over fitting successes that reached index
i, of their running maximum max_{i' <= i} r_{i'} (non-decreasing). An alert needs ``debounce`` consecutive values
above their own T(i). For a whole episode let A = max_i min_{d consecutive} (r_i - q(i)) (log ratio for
``running``): the smallest lambda at which it would never have alerted (-inf with fewer than d values).

The successes are split once (seeded): one half fits the band (``band``) and the shape, the other half gives the
conformal quantiles. Those are grouped into *length regimes* by their number of scored decisions: the bins an
operator sees (edges 20, 40, 80, 160, ...), one regime per bin from the first to the one holding the longest
calibrated episode. A bin holding alpha's minimum of conformal successes (``min_conformal_episodes``: 9 at 0.1, 4 at
0.2, 19 at 0.05; and ``regime_min`` if larger) is *promised*: lambda_B is the split-conformal quantile of A
over its own successes (the r-th smallest, r = ceil((n_B + 1)(1 - alpha))). lambda = max_B lambda_B. A new
successful episode whose length falls in a promised bin B and that is exchangeable with B's calibration successes
then raises *any* alert with probability <= alpha, finite-sample, in every promised bin at once (the shape makes
the bins' lambdas close, so little is lost to the max). A bin with fewer successes carries *no promise*
(a larger ``regime_min`` keeps detection where a quantile of a handful of episodes would bind every earlier index,
and leaves more lengths unpromised): it is never merged into a neighbour (that made the
neighbour's threshold, set by shorter episodes, stand for lengths it did not cover: with 15 of 200 successes at
81-150 decisions, fresh ones alerted at 0.17-0.34 at alpha 0.1); its lengths are judged at the largest promised
level (or, when no bin has enough, the quantile of all successes together, a promise only on average over their
lengths), and an alert raised there says so (``unpromised``). Decisions beyond the longest calibrated episode
(``calibrated_decisions``) keep the last threshold and are flagged likewise. Assumptions: the same task, checkpoint
and set-up; window, debounce, band and shape belong to the calibrated rule (change them and recalibrate).

Detection figures are cross-fitted: every held-out episode is judged by a rule calibrated without it.

One module of about 620 lines on purpose: the rule's pure pieces (band, running statistic, threshold curve, the
calibration per length bin and its promise, cross-fitted figures) in the order a calibration uses them, one
definition that the service, the offline study and the tests all import.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Literal

import numpy as np
from scipy.stats import binomtest

RuleKind = Literal["running", "band"]
RULE_KINDS: tuple[str, ...] = ("running", "band")
SHAPES: tuple[str, ...] = ("flat", "running-max")
BAND_MIN_EPISODES = 3        # successes needed at a decision step before the band has a point there
BAND_SCALE_FLOOR = 0.1       # per-step scale >= this fraction of the pooled scale (a step of identical values)
LOG_FLOOR = 1e-12            # NMSE is >= 0; log of an exact match is floored
SHAPE_MIN_EPISODES = 3       # fitting successes that must reach a decision index for the shape to move there
LENGTH_EDGES = (20, 40, 80, 160, 320, 640, 1280, 2560)   # length regimes, in scored decisions (doubling)
# conformal successes a length bin needs for a promise besides alpha's own minimum: none, so every bin that can
# carry the promise does. A larger minimum (regime_min=20) keeps detection where a bin barely reaches alpha's
# minimum (its quantile, binding every earlier index, is then the largest of a few: PushT at alpha 0.2 alerted on
# 20/51 failures with a 4-success bin promised, 41/51 without), but leaves more lengths unpromised, where the band
# rule's false alerts reached 0.35-0.88 (docs/monitor.md, "The promise")
PROMISE_MIN_SUCCESSES = 1


@dataclass(frozen=True)
class RuleParams:
    """What defines an alert rule; a calibration holds for exactly these values."""

    kind: str = "running"
    window: int = 5
    debounce: int = 2
    clear_ratio: float = 0.8
    shape: str = "flat"

    def __post_init__(self):
        if self.kind not in RULE_KINDS:
            raise ValueError(f"unknown alert rule {self.kind!r}; choose one of {list(RULE_KINDS)}")
        if self.shape not in SHAPES:
            raise ValueError(f"unknown threshold shape {self.shape!r}; choose one of {list(SHAPES)}")
        if self.window < 1 or self.debounce < 1:
            raise ValueError(f"window and debounce must be >= 1, got {self.window} and {self.debounce}")
        if not 0.0 < self.clear_ratio <= 1.0:
            raise ValueError(f"clear_ratio must lie in (0, 1], got {self.clear_ratio}")

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class EpisodeScores:
    """One episode's scored decisions in step order, its outcome and where it ended (env steps)."""

    steps: np.ndarray                 # decision step t of each scored decision, increasing
    nmse: np.ndarray                  # its NMSE
    known_at: np.ndarray              # env step at which that NMSE became known (the target step t + k)
    success: bool | None = None
    end_step: int | None = None       # episode length in env steps, when known
    group: str | None = None
    episode: str = ""

    @property
    def n_decisions(self) -> int:
        return int(np.asarray(self.steps).size)

    @classmethod
    def from_decisions(cls, decisions: list[dict], success: bool | None = None, end_step: int | None = None,
                       group: str | None = None, episode: str = "") -> "EpisodeScores":
        """From [{"step", "target_step", "nmse"}, ...]; decisions without an NMSE are left out."""
        rows = sorted((int(d["step"]), int(d.get("target_step", d["step"])), float(d["nmse"]))
                      for d in decisions if d.get("nmse") is not None)
        steps = np.array([r[0] for r in rows], dtype=np.int64)
        return cls(steps, np.array([r[2] for r in rows], dtype=np.float64),
                   np.array([r[1] for r in rows], dtype=np.int64), success, end_step, group, episode)


# ----------------------------------------------------------------------------------------------------------
# The time-indexed band
# ----------------------------------------------------------------------------------------------------------

@dataclass
class Band:
    """Median and scale of log NMSE of successful episodes at each decision step (knots), piecewise constant:
    a step between knots takes the knot at or before it; a step before the first knot takes the first."""

    steps: list[int]
    center: list[float]
    scale: list[float]

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "Band":
        band = cls([int(s) for s in data["steps"]], [float(c) for c in data["center"]],
                   [float(s) for s in data["scale"]])
        if not band.steps or not len(band.steps) == len(band.center) == len(band.scale):
            raise ValueError("a band needs equally long, non-empty steps, center and scale lists")
        return band

    def standardise(self, steps: np.ndarray, nmse: np.ndarray) -> np.ndarray:
        """z = (log NMSE - center) / scale at each decision's step."""
        knots = np.asarray(self.steps)
        i = np.clip(np.searchsorted(knots, np.asarray(steps), side="right") - 1, 0, len(knots) - 1)
        logs = np.log(np.maximum(np.asarray(nmse, dtype=np.float64), LOG_FLOOR))
        return (logs - np.asarray(self.center)[i]) / np.asarray(self.scale)[i]


def fit_band(episodes: list[EpisodeScores], min_episodes: int = BAND_MIN_EPISODES) -> Band:
    """The band of successful episodes: per decision step with >= ``min_episodes`` values, the median of log
    NMSE and 1.4826 x its median absolute deviation (floored at BAND_SCALE_FLOOR x the pooled scale)."""
    all_steps = np.concatenate([np.asarray(ep.steps, dtype=np.int64) for ep in episodes]) if episodes else \
        np.zeros(0, dtype=np.int64)
    if all_steps.size == 0:
        raise ValueError("no scored decisions to fit a band to")
    logs = np.log(np.maximum(np.concatenate([np.asarray(ep.nmse, dtype=np.float64) for ep in episodes]), LOG_FLOOR))
    pooled_scale = 1.4826 * float(np.median(np.abs(logs - np.median(logs))))
    floor = max(BAND_SCALE_FLOOR * pooled_scale, 1e-6)
    order = np.argsort(all_steps, kind="stable")
    knots, starts, counts = np.unique(all_steps[order], return_index=True, return_counts=True)
    steps, center, scale = [], [], []
    for s, start, count in zip(knots, starts, counts):
        if count < min_episodes:
            continue
        vals = logs[order[start:start + count]]
        med = float(np.median(vals))
        steps.append(int(s))
        center.append(med)
        scale.append(max(1.4826 * float(np.median(np.abs(vals - med))), floor))
    if not steps:   # every step is sparse (very few episodes): one knot from all values
        steps, center, scale = [int(knots[0])], [float(np.median(logs))], [max(pooled_scale, floor)]
    return Band(steps, center, scale)


# ----------------------------------------------------------------------------------------------------------
# The running statistic, the threshold curve and the first alert
# ----------------------------------------------------------------------------------------------------------

def decision_values(params: RuleParams, episode: EpisodeScores, band: Band | None) -> np.ndarray:
    """What the rule takes a running median of: NMSE (``running``) or its band z-score (``band``)."""
    if params.kind == "band":
        if band is None:
            raise ValueError("the band rule needs a fitted band")
        return band.standardise(episode.steps, episode.nmse)
    return np.asarray(episode.nmse, dtype=np.float64)


def running_statistic(values: np.ndarray, window: int) -> np.ndarray:
    """r_i = median of values[max(0, i - window + 1) .. i] for every i (a shorter window at the start)."""
    values = np.asarray(values, dtype=np.float64)
    head = [np.median(values[: i + 1]) for i in range(min(window - 1, values.size))]
    if values.size < window:
        return np.array(head, dtype=np.float64)
    full = np.median(np.lib.stride_tricks.sliding_window_view(values, window), axis=1)
    return np.concatenate([np.asarray(head, dtype=np.float64), full])


def alert_statistic(values: np.ndarray, debounce: int) -> float:
    """A = max_i min(v_{i-d+1..i}): ``debounce`` consecutive values exceed a level T exactly when A > T; -inf
    if too short."""
    values = np.asarray(values, dtype=np.float64)
    if values.size < debounce:
        return -math.inf
    windows = np.lib.stride_tricks.sliding_window_view(values, debounce)
    return float(windows.min(axis=1).max())


def first_alert(running: np.ndarray, threshold, debounce: int) -> int | None:
    """Index of the decision at which ``debounce`` consecutive values above their threshold (a number, or one per
    index) first complete."""
    over = (np.asarray(running, dtype=np.float64) > np.asarray(threshold, dtype=np.float64)).astype(np.int64)
    if over.size < debounce:
        return None
    hits = np.flatnonzero(np.convolve(over, np.ones(debounce, dtype=np.int64), "valid") == debounce)
    return int(hits[0]) + debounce - 1 if hits.size else None


def alert_timing(episode: EpisodeScores, index: int | None, calibrated: int | None = None) -> dict:
    """Where the first alert fell: decision index, its step, the env step at which it was known (its target
    step), the lead before the episode's end (env steps; None when the end is unknown), and whether the index
    lies beyond the ``calibrated`` decisions (no guarantee there)."""
    if index is None:
        return {"alerted": False, "decision_index": None, "step": None, "known_at": None, "lead": None,
                "beyond_calibration": False}
    known = int(episode.known_at[index])
    return {"alerted": True, "decision_index": index, "step": int(episode.steps[index]), "known_at": known,
            "lead": None if episode.end_step is None else int(episode.end_step) - known,
            "beyond_calibration": calibrated is not None and index >= calibrated}


def clear_level(params: RuleParams, threshold: float) -> float:
    """Hysteresis: a raised alert clears after ``debounce`` values below this level. ``running``: clear_ratio x
    threshold (NMSE is positive); ``band``: threshold + ln(clear_ratio) (z-scores of log NMSE may be negative,
    and a ratio on NMSE is a shift of its log)."""
    if params.kind == "band":
        return threshold + math.log(params.clear_ratio)
    return params.clear_ratio * threshold


def excess(params: RuleParams, running: np.ndarray, shape: np.ndarray) -> np.ndarray:
    """How far each running value lies above the shape: r - q (``band``), log(r / q) (``running``)."""
    running = np.asarray(running, dtype=np.float64)
    if params.kind == "band":
        return running - shape
    return np.log(np.maximum(running, LOG_FLOOR)) - np.log(shape)


def threshold_curve(params: RuleParams, shape: np.ndarray, levels) -> np.ndarray:
    """T(i) = q(i) + lambda(i) (``band``) or q(i) x exp(lambda(i)) (``running``)."""
    shape, levels = np.asarray(shape, dtype=np.float64), np.asarray(levels, dtype=np.float64)
    return shape + levels if params.kind == "band" else shape * np.exp(levels)


def fit_shape(runnings: list[np.ndarray], length: int, kind: str,
              min_episodes: int = SHAPE_MIN_EPISODES) -> np.ndarray:
    """q(i) for i < ``length``: the median, over the episodes that reached index i, of their running maximum up
    to i; where fewer than ``min_episodes`` reached it, the value before is held; made non-decreasing. A
    ``running`` shape is floored at LOG_FLOOR (it divides)."""
    if not runnings:
        raise ValueError("no successful episodes to fit the threshold's shape to")
    maxima = np.full((len(runnings), length), np.nan)
    for j, r in enumerate(runnings):
        cm = np.maximum.accumulate(np.asarray(r, dtype=np.float64)[:length])
        maxima[j, : cm.size] = cm
    counts = np.sum(~np.isnan(maxima), axis=0)
    need = min(min_episodes, len(runnings))
    shape = np.empty(length)
    last = None
    for i in range(length):
        if counts[i] >= need or (last is None and counts[i] > 0):
            last = float(np.nanmedian(maxima[:, i]))
        shape[i] = last if last is not None else 0.0
    shape = np.maximum.accumulate(shape)
    return np.maximum(shape, LOG_FLOOR) if kind == "running" else shape


# ----------------------------------------------------------------------------------------------------------
# Calibration
# ----------------------------------------------------------------------------------------------------------

def conformal_rank(n: int, alpha: float) -> int:
    """r = ceil((n+1)(1-alpha)): the threshold is the r-th smallest of n calibration statistics."""
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha must lie in (0, 1), got {alpha}")
    return math.ceil((n + 1) * (1.0 - alpha) - 1e-12)


def min_conformal_episodes(alpha: float) -> int:
    """Smallest n with r <= n, i.e. a finite threshold at ``alpha``: n >= (1 - alpha) / alpha."""
    n = max(1, math.ceil((1.0 - alpha) / alpha) - 1)
    while conformal_rank(n, alpha) > n:   # at most a step or two past the estimate (float rounding)
        n += 1
    return n


def min_successes(alpha: float, params: RuleParams | None = None) -> int:
    """Successful held-out episodes a calibration needs at ``alpha``: one length regime's conformal episodes,
    and (unless nothing is fitted: a flat ``running`` rule) as many less one to fit the band and the shape."""
    m = min_conformal_episodes(alpha)
    if params is not None and params.kind == "running" and params.shape == "flat":
        return m
    return max(2 * m - 1, m + 1)


def fit_split(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Seeded split of n successes: (indices that fit band and shape, indices that give the conformal quantiles)."""
    order = np.random.default_rng(seed).permutation(n)
    n_fit = max(1, n // 2)
    return np.sort(order[:n_fit]), np.sort(order[n_fit:])


@dataclass
class Regime:
    """Calibration successes of lengths (scored decisions) lo..hi, and their conformal quantile of A."""

    lo: int
    hi: int
    n: int
    rank: int               # 0: no promise (too few successes for a finite quantile)
    level: float
    promise: bool = True    # a fresh success of these lengths alerts with probability <= alpha

    def to_dict(self) -> dict:
        return asdict(self)


def length_regimes(lengths: list[int], alpha: float, edges: tuple[int, ...] = LENGTH_EDGES,
                   min_episodes: int | None = None) -> list[tuple[int, int, np.ndarray, bool]]:
    """Group episodes by length into (lo, hi, indices, promised): one group per bin between ``edges``, from the
    first bin to the one holding the longest episode (which ends the top group), empty bins included; a group is
    promised when it holds at least alpha's minimum for a finite conformal quantile (or ``min_episodes``, if
    larger). Bins are never merged: a merged regime's quantile is set by its commoner lengths and promises nothing
    for its scarce ones."""
    lengths = np.asarray(lengths, dtype=np.int64)
    need = max(min_conformal_episodes(alpha), min_episodes or 0)
    bins = np.searchsorted(np.asarray(edges), lengths, side="left")
    bounds, longest = [0, *edges], int(lengths.max())
    out = []
    for b in range(int(bins.max()) + 1):
        idx = np.flatnonzero(bins == b)
        hi = min(edges[b], longest) if b < len(edges) else longest
        out.append((bounds[b] + 1, hi, idx, idx.size >= need))
    return out


@dataclass
class CalibratedRule:
    params: RuleParams
    alpha: float
    level: float            # the largest lambda_B (lambda(i) at the first index)
    shape: np.ndarray       # q(i) for the calibrated decision indices
    band: Band | None
    regimes: list[Regime]
    n_successes: int        # successes the calibration was given
    n_conformal: int        # of which the conformal quantiles used (the rest fit band and shape)
    note: str
    promise_min: int = 1    # conformal successes a bin needed for a promise (besides alpha's minimum)

    @property
    def calibrated_decisions(self) -> int:
        """The longest calibrated episode's scored decisions; later indices hold the last threshold, unguaranteed."""
        return int(self.shape.size)

    @property
    def promise_minimum(self) -> int:
        """Conformal successes a length bin needed for a promise: alpha's minimum, and ``promise_min``."""
        return max(min_conformal_episodes(self.alpha), self.promise_min)

    def _regime_of(self, length: int) -> Regime | None:
        """The regime of the length bin holding ``length`` scored decisions (the top regime covers its whole bin);
        None above the top bin."""
        lo = length_bin(length)[0]
        return next((r for r in self.regimes if r.lo == lo), None)

    def _end(self, regime: Regime) -> int:
        """The longest length a regime covers: its bin's end (the top regime's too, beyond its longest success)."""
        return length_bin(regime.lo)[1]

    def _why(self, what: str) -> str:
        promised = ", ".join(f"{r.lo}-{self._end(r)}" for r in self.regimes if r.promise) or "none"
        return (f"no false-alert promise: {what} (promised lengths: {promised} scored decisions; a promise at "
                f"alpha={self.alpha} needs {self.promise_minimum} held-out successes of a length bin)")

    def unpromised_at_end(self, length: int) -> str:
        """Why no false-alert promise covers the alerts of a successful episode that ended after ``length`` scored
        decisions, or "" when one does (the promise is per final length: its bin must be promised)."""
        if not math.isfinite(self.alpha):   # a labelled (Youden) threshold: it promises nothing, and says so elsewhere
            return ""
        regime = self._regime_of(length)
        if regime is None:
            return self._why(f"the episode ran to {length} scored decisions, longer than any calibration success")
        if regime.promise:
            return ""
        return self._why(f"the episode ended at {length} scored decisions, a length with {regime.n} calibration "
                         "successes")

    def unpromised(self, index: int) -> str:
        """Why no false-alert promise can cover an alert raised at decision ``index`` (0-based: the episode has
        index + 1 scored decisions so far) whatever length the episode ends at, or "" while it may still end in a
        promised bin (whether it did is ``unpromised_at_end``'s, once its length is known)."""
        length = index + 1
        if not math.isfinite(self.alpha) or any(r.promise and length <= self._end(r) for r in self.regimes):
            return ""
        return self._why(f"the episode has run to {length} scored decisions, past every promised length")

    def unpromised_lengths(self) -> list[dict]:
        """The length bins (scored decisions) that carry no promise, with the calibration successes they had."""
        return [{"lo": r.lo, "hi": r.hi, "successes": r.n, "needed": self.promise_minimum}
                for r in self.regimes if not r.promise]

    def levels(self) -> np.ndarray:
        """lambda(i) for the calibrated indices: the largest lambda_B of the regimes an episode that has reached
        index i can still end in (those whose longest length exceeds i)."""
        i = np.arange(self.shape.size)
        out = np.full(self.shape.size, -math.inf)
        for r in self.regimes:
            out = np.where(i < r.hi, np.maximum(out, r.level), out)
        return out

    def thresholds(self, n: int) -> np.ndarray:
        """T(i) for i < n (beyond the calibrated decisions: the last one)."""
        curve = threshold_curve(self.params, self.shape, self.levels())
        if n <= curve.size:
            return curve[:n]
        return np.concatenate([curve, np.full(n - curve.size, curve[-1])])

    def threshold_at(self, index: int) -> float:
        return float(self.thresholds(min(index, self.shape.size - 1) + 1)[-1])

    @property
    def threshold(self) -> float:
        """The threshold at the longest calibrated index, the one held beyond it."""
        return self.threshold_at(self.shape.size - 1)

    def to_dict(self) -> dict:
        return {"params": self.params.to_dict(), "alpha": self.alpha, "level": self.level,
                "threshold": self.threshold, "shape": self.shape.tolist(),
                "band": None if self.band is None else self.band.to_dict(),
                "regimes": [r.to_dict() for r in self.regimes], "unpromised_lengths": self.unpromised_lengths(),
                "calibrated_decisions": self.calibrated_decisions,
                "n_successes": self.n_successes, "n_conformal": self.n_conformal, "note": self.note,
                "promise_min": self.promise_min}

    @classmethod
    def from_dict(cls, data: dict) -> "CalibratedRule":
        """The rule of a stored calibration; KeyError for one made before per-length thresholds (no shape)."""
        return cls(RuleParams(**data["params"]), float(data["alpha"]), float(data["level"]),
                   np.asarray(data["shape"], dtype=np.float64),
                   None if data.get("band") is None else Band.from_dict(data["band"]),
                   [Regime(**r) for r in data["regimes"]], int(data["n_successes"]), int(data["n_conformal"]),
                   str(data.get("note", "")), int(data.get("promise_min", 1)))

    def running(self, episode: EpisodeScores) -> np.ndarray:
        return running_statistic(decision_values(self.params, episode, self.band), self.params.window)

    def judge(self, episode: EpisodeScores) -> dict:
        """Whether the episode alerts, and when (``alert_timing``)."""
        r = self.running(episode)
        index = first_alert(r, self.thresholds(r.size), self.params.debounce)
        return {**alert_timing(episode, index, self.calibrated_decisions),
                "unpromised": "" if index is None else self.unpromised_at_end(r.size)}


def calibrate_rule(successes: list[EpisodeScores], params: RuleParams, alpha: float, seed: int = 0,
                   edges: tuple[int, ...] = LENGTH_EDGES, regime_min: int = PROMISE_MIN_SUCCESSES) -> CalibratedRule:
    """The threshold curve of ``params`` at false-alert rate ``alpha`` in every length regime, from held-out
    successful episodes (module docstring).

    Raises ValueError naming how many successes are needed when there are too few, and when most successes are
    too short to be judged at all (fewer scored decisions than ``debounce``).
    """
    n = len(successes)
    need = min_successes(alpha, params)
    if n < need:
        raise ValueError(
            f"the {params.kind} rule at alpha={alpha} needs at least {need} successful held-out episodes with scored "
            f"decisions, got {n}; record {need - n} more (or raise alpha)")
    if params.kind == "running" and params.shape == "flat":
        fit_idx, conf_idx = np.zeros(0, dtype=np.int64), np.arange(n)
    else:
        fit_idx, conf_idx = fit_split(n, seed)
    fit = [successes[i] for i in fit_idx]
    band = fit_band(fit) if params.kind == "band" else None
    fit_running = [running_statistic(decision_values(params, e, band), params.window) for e in fit]
    conf_running = [running_statistic(decision_values(params, successes[i], band), params.window) for i in conf_idx]
    lengths = [r.size for r in conf_running]
    if params.shape == "flat":
        shape = np.full(max(lengths), 1.0 if params.kind == "running" else 0.0)
    else:
        shape = fit_shape(fit_running, max(lengths), params.kind)
    stats = np.array([alert_statistic(excess(params, r, shape[: r.size]), params.debounce) for r in conf_running])
    groups = length_regimes(lengths, alpha, edges, regime_min)
    levels = {}
    for lo, hi, idx, promised in groups:
        if promised:
            rank = conformal_rank(idx.size, alpha)
            levels[lo] = (rank, float(np.sort(stats[idx])[rank - 1]))
    if levels:
        base = max(level for _, level in levels.values())
    else:   # no bin holds enough: all successes together, a promise only on average over their lengths
        base = float(np.sort(stats)[conformal_rank(stats.size, alpha) - 1])
    regimes = [Regime(lo, hi, int(idx.size), *levels.get(lo, (0, base)), promise=lo in levels)
               for lo, hi, idx, _ in groups]
    level = max(r.level for r in regimes)
    if not math.isfinite(level):
        raise ValueError(
            f"most successful episodes have fewer than {params.debounce} scored decisions, too few to be judged by a "
            f"rule with debounce {params.debounce}; lower the debounce or record longer episodes")
    promised = [r for r in regimes if r.promise]
    unpromised = [r for r in regimes if not r.promise]
    note = (f"lambda(i) = max over the {len(promised)} promised length bin(s) still open at index i of the "
            f"ceil((n+1)(1-alpha))-th smallest alert statistic ("
            + (", ".join(f"{r.lo}-{r.hi} decisions: {r.n}" for r in promised) or "none") + " successes)"
            + (f"; no promise at {', '.join(f'{r.lo}-{r.hi} decisions ({r.n} successes)' for r in unpromised)}: "
               f"a promise at alpha={alpha} needs {max(min_conformal_episodes(alpha), regime_min)} per bin"
               + ("" if promised else ", so the level is the quantile of all lengths together") if unpromised else "")
            + "; " + (f"band and shape fitted on the other {len(fit)}" if fit else "nothing fitted"))
    return CalibratedRule(params, alpha, level, shape, band, regimes, n, len(conf_idx), note, regime_min)


# ----------------------------------------------------------------------------------------------------------
# Cross-fitted detection figures
# ----------------------------------------------------------------------------------------------------------

def binomial_ci(k: int, n: int, level: float = 0.95) -> list[float] | None:
    """Clopper-Pearson interval of a rate k / n (None when n = 0)."""
    if n == 0:
        return None
    ci = binomtest(k, n).proportion_ci(confidence_level=level, method="exact")
    return [float(ci.low), float(ci.high)]


def _quartiles(values: list[float]) -> dict | None:
    if not values:
        return None
    q1, med, q3 = np.percentile(np.asarray(values, dtype=np.float64), [25, 50, 75])
    return {"median": float(med), "q1": float(q1), "q3": float(q3), "n": len(values)}


def folds_of(episodes: list[EpisodeScores], k: int, seed: int) -> list[np.ndarray]:
    """k folds stratified by group and outcome (each group's successes and failures spread over the folds)."""
    rng = np.random.default_rng(seed)
    fold_of = np.empty(len(episodes), dtype=np.int64)
    keys = sorted({(str(e.group), bool(e.success)) for e in episodes})
    for key in keys:
        idx = np.array([i for i, e in enumerate(episodes) if (str(e.group), bool(e.success)) == key])
        fold_of[rng.permutation(idx)] = np.arange(idx.size) % k
    return [np.flatnonzero(fold_of == f) for f in range(k)]


def cross_fit(episodes: list[EpisodeScores], params: RuleParams, alpha: float, k: int = 5, seed: int = 0,
              within_groups: bool = False) -> dict:
    """Detection figures of a rule, each episode judged by the rule calibrated on the successes of the other
    folds: of all groups (as a calibration pools what it is given), or with ``within_groups`` of its own group
    only (one calibration per checkpoint, as the main job calibrates).

    Returns the false-alert rate on successes and the true-alert rate on failures (with Clopper-Pearson 95 %
    intervals), detection time (decision index and the env step at which the alert was known) and lead before
    the episode's end as median and quartiles, and how many episodes no fold could judge (too few successes).
    """
    figures = cross_fit_with(episodes, lambda train: calibrate_rule(train, params, alpha, seed), k, seed,
                             within_groups)
    return {"rule": params.to_dict(), "alpha": alpha, **figures}


def cross_fit_with(episodes: list, fit, k: int = 5, seed: int = 0, within_groups: bool = False,
                   with_failures: bool = False) -> dict:
    """``cross_fit`` for any ``fit(train_successes) -> object with judge(episode)`` that raises ValueError when
    the training successes cannot support it (those episodes are counted as skipped); ``with_failures``: fit gets
    the training folds' failures too."""
    judged = {True: [], False: []}
    skipped = 0
    group_of = (lambda e: str(e.group)) if within_groups else (lambda e: "")
    for test in folds_of(episodes, k, seed):
        test_set = set(test.tolist())
        for group in sorted({group_of(episodes[i]) for i in test}):
            train = [e for i, e in enumerate(episodes)
                     if i not in test_set and group_of(e) == group and (e.success or with_failures)]
            members = [episodes[i] for i in test if group_of(episodes[i]) == group]
            try:
                rule = fit(train)
            except ValueError:
                skipped += len(members)
                continue
            for e in members:
                judged[bool(e.success)].append({**rule.judge(e), "length": e.n_decisions})
    fa = sum(j["alerted"] for j in judged[True])
    ta = sum(j["alerted"] for j in judged[False])
    hits = [j for j in judged[False] if j["alerted"]]
    return {
        "folds": k,
        "successes": len(judged[True]),
        "failures": len(judged[False]),
        "false_alerts": fa,
        "false_alert_rate": fa / len(judged[True]) if judged[True] else None,
        "false_alert_ci": binomial_ci(fa, len(judged[True])),
        "true_alerts": ta,
        "true_alert_rate": ta / len(judged[False]) if judged[False] else None,
        "true_alert_ci": binomial_ci(ta, len(judged[False])),
        "detection_decision": _quartiles([j["decision_index"] for j in hits]),
        "detection_step": _quartiles([j["known_at"] for j in hits]),
        "lead_steps": _quartiles([j["lead"] for j in hits if j["lead"] is not None]),
        "false_alerts_by_length": by_length(judged[True]),
        "alerts_beyond_calibration": sum(bool(j.get("beyond_calibration")) for j in judged[True] + judged[False]),
        # alerts on episodes that could still end at a length the fold's calibration promised nothing for
        "alerts_unpromised": sum(bool(j.get("unpromised")) for j in judged[True] + judged[False]),
        "false_alerts_unpromised": sum(bool(j.get("unpromised")) for j in judged[True]),
        "skipped_episodes": skipped,
    }


def length_bin(length: int, edges: tuple[int, ...] = LENGTH_EDGES) -> tuple[int, int]:
    """The (lo, hi) bin of LENGTH_EDGES an episode of ``length`` scored decisions falls in."""
    i = int(np.searchsorted(np.asarray(edges), length, side="left"))
    return (1 if i == 0 else edges[i - 1] + 1), (edges[i] if i < len(edges) else 10**9)


def by_length(judged: list[dict]) -> list[dict]:
    """Alert counts of judged episodes ({"length", "alerted"}) per length bin, with Clopper-Pearson intervals."""
    bins: dict[tuple[int, int], list[int]] = {}
    for j in judged:
        k_n = bins.setdefault(length_bin(j["length"]), [0, 0])
        k_n[0] += bool(j["alerted"])
        k_n[1] += 1
    return [{"lo": lo, "hi": hi, "alerts": k, "episodes": n, "rate": k / n, "ci": binomial_ci(k, n)}
            for (lo, hi), (k, n) in sorted(bins.items())]
