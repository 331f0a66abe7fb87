"""Detectors over named per-decision scores: one signal's calibrated rule, or two or more combined, as pure
functions the service and an offline study share.

A *signal* is one non-negative per-decision risk score, larger = riskier: ``nmse`` (the future-consistency error
the service computes from the latents), ``nmse_ratio`` (that error over the persistence control's, computed when
a decision also sent z_now) or any score a robot loop sends by name (e.g. ``stac``, the distance
between consecutive action chunks; ``rnd``, a random-network-distillation error on the embedding). Each signal
gets its own calibrated rule (``rules.py``: running statistic, per-length threshold, debounce). A detector says
which signals alert and how:

- ``single``: one signal's rule; at most alpha of successful episodes alert (in each length regime).
- ``fiper`` (FIPER, Roemer et al. 2025): an alarm when two signals' rules both exceed their thresholds at the same
  decision, each calibrated at alpha. The alarm needs the first signal's alarm, so P(false alarm) <= alpha.
- ``bonferroni``: an alarm when any of K signals' rules exceeds its threshold, each calibrated at alpha / K. Each
  rule's alarm is a calibrated p-value test (conformal p-value of its alert statistic <= alpha / K), so the
  union bound gives P(false alarm) <= alpha: the min-p fusion of calibrated per-signal p-values.

Two ways to calibrate a signal's threshold:

- ``successes`` (FAIL-Detect and FIPER's way, and the service's): the split-conformal quantile over successful
  held-out rollouts, with the false-alert guarantee.
- ``labelled`` (the paper's way of reading labelled episodes, Sec. 4.10): the level that maximises Youden's J
  (true-alert rate - false-alert rate) of the episodes' alert statistic over labelled successes and failures.
  It promises nothing about false alerts; a study measures them on held-out episodes.

The offline study's entry point is :func:`study_alerts`.
"""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from monitor_service import rules
from monitor_service.scoring import NMSE, RATIO, SERVICE_SIGNALS  # noqa: F401  (the service's own signals, re-exported)

COMBINATIONS: tuple[str, ...] = ("single", "fiper", "bonferroni")
CALIBRATIONS: tuple[str, ...] = ("successes", "labelled")


@dataclass
class SignalEpisode:
    """One episode's per-decision scores by signal name (NaN where a decision lacks that signal), its outcome and,
    optionally, the decisions' env steps (default 0, 1, 2, ...) and the env step at which each signal's value
    became known (default: the decision's step; NMSE is known at the target step t + k)."""

    scores: Mapping[str, np.ndarray]
    success: bool | None = None
    steps: np.ndarray | None = None
    known_at: Mapping[str, np.ndarray] = field(default_factory=dict)
    end_step: int | None = None
    group: str | None = None
    episode: str = ""

    def __post_init__(self):
        lengths = {name: np.asarray(v).size for name, v in self.scores.items()}
        if len(set(lengths.values())) > 1:
            raise ValueError(f"episode {self.episode!r}: every signal needs one value per decision (NaN where "
                             f"missing), got lengths {lengths}")
        n = next(iter(lengths.values()), 0)
        if self.steps is not None and np.asarray(self.steps).size != n:
            raise ValueError(f"episode {self.episode!r}: {np.asarray(self.steps).size} steps for {n} decisions")

    @property
    def n_decisions(self) -> int:
        return int(np.asarray(next(iter(self.scores.values()), [])).size)

    def series(self, signal: str) -> rules.EpisodeScores:
        """The signal's scored decisions in step order (a rule's input)."""
        if signal not in self.scores:
            raise KeyError(signal)
        values = np.asarray(self.scores[signal], dtype=np.float64)
        steps = np.arange(values.size, dtype=np.int64) if self.steps is None else np.asarray(self.steps, np.int64)
        known = np.asarray(self.known_at.get(signal, steps), dtype=np.int64)
        keep = np.isfinite(values)
        order = np.argsort(steps[keep], kind="stable")
        return rules.EpisodeScores(steps[keep][order], values[keep][order], known[keep][order], self.success,
                                   self.end_step, self.group, self.episode)


@dataclass(frozen=True)
class DetectorSpec:
    """Which signals alert, how they combine, how their thresholds are calibrated, and the rule they run."""

    signals: tuple[str, ...]
    combination: str = "single"
    calibration: str = "successes"
    params: rules.RuleParams = rules.RuleParams("band")

    def __post_init__(self):
        object.__setattr__(self, "signals", tuple(self.signals))
        if self.combination not in COMBINATIONS:
            raise ValueError(f"unknown combination {self.combination!r}; choose one of {list(COMBINATIONS)}")
        if self.calibration not in CALIBRATIONS:
            raise ValueError(f"unknown calibration {self.calibration!r}; choose one of {list(CALIBRATIONS)}")
        need = {"single": (1, 1), "fiper": (2, 2), "bonferroni": (2, 64)}[self.combination]
        if not need[0] <= len(self.signals) <= need[1] or len(set(self.signals)) != len(self.signals):
            raise ValueError(f"a {self.combination} detector takes {need[0]}" + ("" if need[0] == need[1] else
                             f" to {need[1]}") + f" distinct signals, got {list(self.signals)}")

    @property
    def name(self) -> str:
        """e.g. ``stac``, ``fiper(stac+rnd)``, ``bonferroni(nmse+stac+rnd)``, with ``[labelled]`` and the rule."""
        base = self.signals[0] if self.combination == "single" else f"{self.combination}({'+'.join(self.signals)})"
        return f"{base} {self.params.kind}" + (" [labelled]" if self.calibration == "labelled" else "")

    def signal_alpha(self, alpha: float) -> float:
        """The level each signal's rule is calibrated at: alpha / K for bonferroni, else alpha."""
        return alpha / len(self.signals) if self.combination == "bonferroni" else alpha

    def to_dict(self) -> dict:
        return {"signals": list(self.signals), "combination": self.combination, "calibration": self.calibration,
                "params": self.params.to_dict()}

    @classmethod
    def from_dict(cls, data: dict) -> "DetectorSpec":
        return cls(tuple(data["signals"]), data["combination"], data["calibration"], rules.RuleParams(**data["params"]))


@dataclass
class SignalFlags:
    """One signal's rule over one episode: per scored decision its step, when it was known, the running value,
    its threshold, and whether the last ``debounce`` values were all above their thresholds (over) or all below
    their clear levels (under)."""

    steps: np.ndarray
    known_at: np.ndarray
    values: np.ndarray
    thresholds: np.ndarray
    over: np.ndarray
    under: np.ndarray
    calibrated: int

    @classmethod
    def of(cls, rule: rules.CalibratedRule, series: rules.EpisodeScores) -> "SignalFlags":
        values = rule.running(series)
        thresholds = rule.thresholds(values.size)
        clear = np.array([rules.clear_level(rule.params, t) for t in thresholds])
        d = rule.params.debounce
        return cls(np.asarray(series.steps), np.asarray(series.known_at), values, thresholds,
                   _runs(values > thresholds, d), _runs(values < clear, d), rule.calibrated_decisions)


def _runs(hit: np.ndarray, d: int) -> np.ndarray:
    """True where the last ``d`` entries (this one included) are all True."""
    out = np.zeros(hit.size, dtype=bool)
    if hit.size >= d:
        out[d - 1:] = np.convolve(hit.astype(np.int64), np.ones(d, dtype=np.int64), "valid") == d
    return out


@dataclass
class CalibratedDetector:
    spec: DetectorSpec
    alpha: float
    rules: dict[str, rules.CalibratedRule]
    note: str = ""

    def to_dict(self) -> dict:
        return {"spec": self.spec.to_dict(), "alpha": self.alpha, "note": self.note,
                "rules": {name: rule.to_dict() for name, rule in self.rules.items()}}

    @classmethod
    def from_dict(cls, data: dict) -> "CalibratedDetector":
        return cls(DetectorSpec.from_dict(data["spec"]), float(data["alpha"]),
                   {name: rules.CalibratedRule.from_dict(r) for name, r in data["rules"].items()}, data.get("note", ""))

    def _combined(self, why: dict[str, str]) -> str:
        """One reason from each signal's (``single``: its own; ``fiper``, where both must alert: none while
        either signal's promise holds; ``bonferroni``, where any may alert: every signal's promise is needed)."""
        if self.spec.combination == "fiper" and not all(why.values()):
            return ""
        return "; ".join(sorted({w for w in why.values() if w}))

    def unpromised_at_end(self, lengths: dict[str, int]) -> str:
        """Why no false-alert promise covers an alert of an episode whose signals ended with these numbers of
        values, or "" when one does."""
        return self._combined({s: self.rules[s].unpromised_at_end(n) for s, n in lengths.items() if s in self.rules})

    def unpromised_now(self, lengths: dict[str, int]) -> str:
        """Why no promise can cover an alert raised now, the signals having these numbers of values, whatever
        length the episode ends at; "" while it may still end where one holds."""
        return self._combined({s: self.rules[s].unpromised(n - 1) for s, n in lengths.items()
                               if s in self.rules and n > 0})

    def flags(self, episode: SignalEpisode) -> dict[str, SignalFlags]:
        """Each signal's flags over the episode (a signal the episode lacks is left out)."""
        return {s: SignalFlags.of(self.rules[s], episode.series(s)) for s in self.spec.signals if s in episode.scores}

    def judge(self, episode: SignalEpisode) -> dict:
        """Whether the episode alerts, at which decision step, which signals raised it, whether beyond the
        calibrated length, why no false-alert promise covers its alert (``unpromised``: "" when one does), the env
        step at which it was known and the lead before the episode's end."""
        flags = self.flags(episode)
        hit = None   # (step, known_at, signals, beyond, index)
        if self.spec.combination == "fiper":
            if len(flags) == 2:
                (a, fa), (b, fb) = flags.items()
                over_a = {int(s): i for s, i in zip(fa.steps[fa.over], np.flatnonzero(fa.over))}
                for j in np.flatnonzero(fb.over):
                    i = over_a.get(int(fb.steps[j]))
                    if i is not None:
                        hit = (int(fb.steps[j]), int(max(fa.known_at[i], fb.known_at[j])), [a, b],
                               i >= fa.calibrated or j >= fb.calibrated, int(j))
                        break
        else:
            for name, f in flags.items():
                i = np.flatnonzero(f.over)
                if i.size and (hit is None or f.steps[i[0]] < hit[0]):
                    hit = (int(f.steps[i[0]]), int(f.known_at[i[0]]), [name], bool(i[0] >= f.calibrated), int(i[0]))
        if hit is None:
            return {"alerted": False, "step": None, "decision_index": None, "known_at": None, "signals": [],
                    "beyond_calibration": False, "unpromised": "", "lead": None}
        step, known, signals, beyond, index = hit
        return {"alerted": True, "step": step, "decision_index": index, "known_at": known, "signals": signals,
                "beyond_calibration": beyond,
                "unpromised": self.unpromised_at_end({s: int(f.steps.size) for s, f in flags.items()}),
                "lead": None if episode.end_step is None else int(episode.end_step) - known}


def labelled_rule(successes: list[rules.EpisodeScores], failures: list[rules.EpisodeScores],
                  params: rules.RuleParams, seed: int = 0) -> rules.CalibratedRule:
    """The rule whose level maximises Youden's J = true-alert rate - false-alert rate of the alert statistic over
    labelled episodes (band and shape fitted on half of the successes, as for ``successes``); ties: the highest
    level. No false-alert guarantee."""
    template = rules.calibrate_rule(successes, params, 0.5, seed, regime_min=1)   # fits band and shape
    fit_idx, conf_idx = (np.zeros(0, int), np.arange(len(successes))) \
        if params.kind == "running" and params.shape == "flat" else rules.fit_split(len(successes), seed)

    def statistic(e):
        r = rules.running_statistic(rules.decision_values(params, e, template.band), params.window)
        shape = np.concatenate([template.shape, np.full(max(0, r.size - template.shape.size), template.shape[-1])])
        return rules.alert_statistic(rules.excess(params, r, shape[: r.size]), params.debounce)

    s = np.array([statistic(successes[i]) for i in conf_idx])
    f = np.array([statistic(e) for e in failures])
    if not failures:
        raise ValueError("a labelled calibration needs failed held-out episodes too; record some, or calibrate on "
                         "successes")
    candidates = np.unique(np.concatenate([s, f]))
    best, level = -math.inf, float(candidates[-1])
    for c in candidates[::-1]:   # from the highest level down: ties keep the higher one
        j = float(np.mean(f > c)) - float(np.mean(s > c))
        if j > best:
            best, level = j, float(c)
    regime = rules.Regime(1, template.calibrated_decisions, int(s.size), 0, level)
    return replace(template, alpha=math.nan, level=level, regimes=[regime],
                   note=f"labelled: Youden's J = {best:.3f} over {s.size} successes and {f.size} failures; no "
                        "false-alert guarantee")


def calibrate_detector(spec: DetectorSpec, episodes: Sequence[SignalEpisode], alpha: float,
                       seed: int = 0) -> CalibratedDetector:
    """Each of the detector's signals calibrated on the labelled episodes that carry it (``successes``: their
    successes only). Raises ValueError naming the signal and the fix when the episodes cannot support it."""
    calibrated = {}
    for signal in spec.signals:
        series = [e.series(signal) for e in episodes if signal in e.scores and e.success is not None]
        series = [s for s in series if s.steps.size]
        successes = [s for s in series if s.success]
        try:
            if spec.calibration == "successes":
                calibrated[signal] = rules.calibrate_rule(successes, spec.params, spec.signal_alpha(alpha), seed)
            else:
                calibrated[signal] = labelled_rule(successes, [s for s in series if not s.success], spec.params, seed)
        except ValueError as exc:
            raise ValueError(f"signal {signal!r}: {exc}") from None
    note = {"single": f"at most {alpha:g} of successful episodes alert in each length regime",
            "fiper": f"an alarm needs both signals over their thresholds (each calibrated at {alpha:g}): at most "
                     f"{alpha:g} of successful episodes alert",
            "bonferroni": f"an alarm when any of {len(spec.signals)} signals is over its threshold (each calibrated "
                          f"at {spec.signal_alpha(alpha):g}): at most {alpha:g} of successful episodes alert"
            }[spec.combination]
    if spec.calibration == "labelled":
        note = "labelled (Youden) thresholds: no false-alert guarantee"
    return CalibratedDetector(spec, alpha, calibrated, note)


def cross_fit_detector(episodes: Sequence[SignalEpisode], spec: DetectorSpec, alpha: float, k: int = 5,
                       seed: int = 0, within_groups: bool = False) -> dict:
    """``rules.cross_fit`` for a detector: every episode judged by the detector calibrated on the other folds
    (their successes, and their failures too for a ``labelled`` calibration)."""
    figures = rules.cross_fit_with(list(episodes), lambda train: calibrate_detector(spec, train, alpha, seed), k, seed,
                                   within_groups, with_failures=spec.calibration == "labelled")
    return {"detector": spec.name, "rule": spec.params.to_dict(), "alpha": alpha, **figures}


def default_detectors(signals: Sequence[str], params: rules.RuleParams = rules.RuleParams("band")
                      ) -> list[DetectorSpec]:
    """The comparison a study runs: every signal alone (calibrated on successes, and on labelled episodes),
    FIPER's rule on every pair, and the Bonferroni fusion of all of them."""
    signals = list(signals)
    out = [DetectorSpec((s,), "single", cal, params) for s in signals for cal in CALIBRATIONS]
    out += [DetectorSpec((a, b), "fiper", "successes", params) for i, a in enumerate(signals) for b in signals[i + 1:]]
    if len(signals) > 1:
        out.append(DetectorSpec(tuple(signals), "bonferroni", "successes", params))
    return out


def study_judgements(calibration: Sequence[SignalEpisode], test: Sequence[SignalEpisode], alpha: float,
                     detectors: Sequence[DetectorSpec] | None = None, seed: int = 0
                     ) -> tuple[dict[str, list[dict]], dict[str, str]]:
    """Every detector (default: :func:`default_detectors` of the calibration's signals) calibrated on the
    labelled ``calibration`` episodes at ``alpha`` and judged on each ``test`` episode. Returns (detector name ->
    one ``CalibratedDetector.judge`` dict per test episode, detector name -> why the calibration episodes could
    not support it, e.g. too few successes at alpha)."""
    signals = sorted({s for e in calibration for s in e.scores})
    judged, refused = {}, {}
    for spec in detectors if detectors is not None else default_detectors(signals):
        try:
            detector = calibrate_detector(spec, calibration, alpha, seed)
        except ValueError as exc:
            refused[spec.name] = str(exc)
            continue
        judged[spec.name] = [detector.judge(e) for e in test]
    return judged, refused


def study_alerts(calibration: Sequence[SignalEpisode], test: Sequence[SignalEpisode], alpha: float,
                 detectors: Sequence[DetectorSpec] | None = None, seed: int = 0) -> dict[str, list[int | None]]:
    """The offline study's API: each detector (default: :func:`default_detectors` of the calibration's signals)
    calibrated on the labelled ``calibration`` episodes at ``alpha``, then for every ``test`` episode the
    decision step of its first alert, or None when it raised none. Detectors the calibration cannot support are
    left out (:func:`study_judgements` says why)."""
    return {name: [j["step"] for j in judged]
            for name, judged in study_judgements(calibration, test, alpha, detectors, seed)[0].items()}
