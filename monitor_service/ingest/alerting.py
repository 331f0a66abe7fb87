"""Per episode after its records are applied: the early and running scores, and the active calibration's
detector stepped over each of its signals' values scored since the last evaluation (``rules.py`` and
``signals.py`` are the same rules, offline).

Each alerting signal keeps its own state in ``EpisodeState.signal_state``: the last evaluated step, how many
consecutive values were above their thresholds (over) and below their clear levels (under), its latest value and
threshold, and (for FIPER's rule) its recent over flags by step. A signal is *over* at a decision when its last
``debounce`` values exceeded their thresholds, *under* when they lay below their clear levels. The detector
raises when its signal is over (``single``), when any is (``bonferroni``), or when both are over at the same
decision (``fiper``); a raised alert clears when every signal it combines is under.
"""
from __future__ import annotations

import statistics
import time
from bisect import bisect_right

import numpy as np

from monitor_service import rules, scoring
from monitor_service.ingest import sql as statements
from monitor_service.ingest.sql import Sql
from monitor_service.ingest.state import EpisodeState, Request
from monitor_service.settings import MonitorSettings
from monitor_service.signals import RATIO, CalibratedDetector, DetectorSpec

CALIBRATION_TTL_S = 1.0      # another process's new calibration is seen within this time
FLAGS_KEPT = 64              # recent over flags per signal (FIPER's partner may be scored a little later)


def rule_params(settings: MonitorSettings, kind: str | None = None, shape: str | None = None) -> rules.RuleParams:
    """The alert rule the service runs now: window, debounce and hysteresis from the settings; kind and threshold
    shape the calibration's (or the settings' for a new one)."""
    return rules.RuleParams(kind or settings.alert_rule, settings.running_window, settings.alert_debounce,
                            settings.alert_clear_ratio, shape or settings.threshold_shape)


def stored_detector(result: dict) -> CalibratedDetector:
    """The detector of a calibration's result (one made before named signals: its NMSE rule alone). KeyError for
    a calibration made before per-length thresholds."""
    if "detector" in result:
        return CalibratedDetector.from_dict(result["detector"])
    rule = rules.CalibratedRule.from_dict(result["rule"])
    return CalibratedDetector(DetectorSpec(("nmse",), params=rule.params), rule.alpha,
                                        {"nmse": rule})


class Alerting:
    """The active calibrations' detectors (cached briefly) and their evaluation over an episode's new scores."""

    def __init__(self, sql: Sql, settings: MonitorSettings):
        self.sql = sql
        self.settings = settings
        self.calibrations: dict[tuple[str, str | None], tuple[float, tuple[int | None, dict | None]]] = {}
        self.detectors: dict[int, CalibratedDetector] = {}

    def forget_calibrations(self) -> None:
        self.calibrations.clear()

    def _calibration(self, cur, task: str, checkpoint: str | None) -> tuple[int | None, dict | None]:
        key = (task, checkpoint)
        hit = self.calibrations.get(key)
        now = time.monotonic()
        if hit is not None and now - hit[0] < CALIBRATION_TTL_S:
            return hit[1]
        found = statements.active_calibration(self.sql, cur, task, checkpoint)
        self.calibrations[key] = (now, found)
        return found

    def calibrated_signals(self, cur, task: str, checkpoint: str | None) -> tuple[int, frozenset[str]] | None:
        """(id, the signals it has data for) of the active calibration, or None without one."""
        cal_id, result = self._calibration(cur, task, checkpoint)
        if cal_id is None:
            return None
        return cal_id, frozenset(result.get("signals", {}) or ("nmse",))

    def usable_detector(self, cur, ep: EpisodeState) -> tuple[int | None, CalibratedDetector | None, str]:
        """(calibration id, its detector or None when it cannot alert, the episode's alert note saying why)."""
        cal_id, result = self._calibration(cur, ep.task, ep.checkpoint)
        fix = f"`jepa-monitor calibrate --task {ep.task}` (or POST /v1/calibrations)"
        if cal_id is None:
            return None, None, (f"no alerts: task {ep.task!r} has no active calibration; record held-out labelled "
                                f"episodes and run {fix}")
        if "rule" not in result:
            return cal_id, None, (f"no alerts: calibration #{cal_id} predates episode-level alert rules (its "
                                  f"threshold covered the early score only); recalibrate with {fix}")
        if "shape" not in result["rule"]:
            return cal_id, None, (f"no alerts: calibration #{cal_id} predates per-length thresholds (its false-alert "
                                  f"guarantee held only on average over episode lengths); recalibrate with {fix}")
        if "unpromised_lengths" not in result["rule"]:
            return cal_id, None, (f"no alerts: calibration #{cal_id} predates per-length promises (it merged length "
                                  "bins with few successes into their neighbours, whose shorter episodes set the "
                                  f"threshold, and said nothing); recalibrate with {fix}")
        if cal_id not in self.detectors:
            self.detectors[cal_id] = stored_detector(result)
        detector = self.detectors[cal_id]
        made = detector.spec.params
        now = rule_params(self.settings, made.kind, made.shape)
        if made != now:
            return cal_id, None, (
                f"no alerts: calibration #{cal_id} holds for window={made.window}, debounce={made.debounce}, clear "
                f"ratio={made.clear_ratio}, but the service runs window={now.window}, debounce={now.debounce}, clear "
                f"ratio={now.clear_ratio}; its false-alert guarantee does not cover that rule, so recalibrate with "
                f"{fix}")
        first = detector.rules[detector.spec.signals[0]]
        blind = ""
        if RATIO in detector.spec.signals and ep.scored and not ep.values(RATIO):
            blind = ("; no nmse_ratio yet: this episode's scored decisions sent no z_now (send z_now, the current "
                     "latent, with each decision)")
        return cal_id, detector, (
            f"alerting with {detector.spec.name}: {made.debounce} consecutive values of the {made.kind} statistic "
            f"(median of {made.window}) above their decision's threshold (up to {first.threshold:.6g} for "
            f"{detector.spec.signals[0]}): calibration #{cal_id}, {detector.note} up to "
            f"{first.calibrated_decisions} scored decisions{blind}")

    def early_score(self, ep: EpisodeState) -> None:
        """The early score from the first decisions of the episode's decision grid only (published once all of
        them are scored); a change of a published value is counted as a revision."""
        n = self.settings.early_decisions
        grid = ep.grid_steps(n)
        early = None
        if grid is not None and all(s in ep.decisions for s in grid):
            early = scoring.early_score([ep.decisions[s].nmse for s in grid], n)
        if ep.early_score is not None and early != ep.early_score:
            ep.early_revisions += 1
        ep.early_score = early

    def refresh(self, cur, req: Request, ep: EpisodeState) -> None:
        """Early score, running NMSE, and the detector over each signal's values scored since its last evaluated
        step, in step order, each judged against its index's threshold. A value scored after a later one was
        evaluated counts for the scores but is not evaluated for alerts."""
        self.early_score(ep)
        ep.n_scored += req.newly_scored.get(ep.id, 0)
        window = self.settings.running_window
        running = scoring.running_score([v for _, v in ep.scored[-window:]], window)
        if running is not None:
            ep.running_score = running
        state = dict(ep.signal_state or {})
        signals = {"nmse"} | set(ep.series)
        todo = any(self._new(ep, state, s) for s in signals)
        if not todo:
            return
        cal_id, detector, ep.alert_note = self.usable_detector(cur, ep)
        if detector is None:   # nothing to judge with: mark every value as seen
            for s in signals:
                values = ep.values(s)
                if values:
                    state[s] = {**state.get(s, {}), "last": values[-1][0]}
            ep.last_evaluated_step = ep.scored[-1][0] if ep.scored else ep.last_evaluated_step
            ep.signal_state = state
            ep.risk_threshold = ep.calibrated_decisions = None
            return
        events = []
        for s in detector.spec.signals:
            events += self._step_signal(ep, state, s, detector.rules[s])
        events.sort(key=lambda e: e[0])   # decision step order across signals (stable within a signal)
        for step, signal, over, under, value, threshold, beyond in events:
            self._judge(cur, req, ep, state, detector, cal_id, step, signal, over, under, value, threshold, beyond)
        first = detector.spec.signals[0]
        st = state.get(first, {})
        ep.last_evaluated_step = st.get("last", ep.last_evaluated_step)
        ep.over_count, ep.under_count = st.get("over", 0), st.get("under", 0)
        if "value" in st:
            ep.risk_score, ep.risk_threshold = st["value"], st["threshold"]
        ep.calibrated_decisions = detector.rules[first].calibrated_decisions
        ep.signal_state = state

    @staticmethod
    def _new(ep: EpisodeState, state: dict, signal: str) -> bool:
        values = ep.values(signal)
        last = state.get(signal, {}).get("last", ep.last_evaluated_step if signal == "nmse" else -1)
        return bool(values) and values[-1][0] > last

    def _step_signal(self, ep: EpisodeState, state: dict, signal: str, rule: rules.CalibratedRule) -> list[tuple]:
        """Advance one signal's rule over its values after its last evaluated step: (step, signal, over, under,
        value, threshold, beyond the calibrated length) per value."""
        series = ep.values(signal)
        st = dict(state.get(signal) or {"last": ep.last_evaluated_step if signal == "nmse" else -1,
                                        "over": ep.over_count if signal == "nmse" else 0,
                                        "under": ep.under_count if signal == "nmse" else 0})
        st["flags"] = dict(st.get("flags", {}))
        first_new = bisect_right(series, (st["last"], float("inf")))
        if first_new >= len(series):
            return []
        window, debounce = rule.params.window, rule.params.debounce
        lo = max(0, first_new + 1 - window)
        part = series[lo:]
        steps = np.array([s for s, _ in part], dtype=np.int64)
        values = rules.decision_values(rule.params, rules.EpisodeScores(steps, np.array([v for _, v in part]), steps),
                                       rule.band).tolist()
        thresholds = rule.thresholds(len(series)).tolist()
        out = []
        for i in range(first_new, len(series)):
            j = i - lo
            value = float(statistics.median(values[max(0, j + 1 - window): j + 1]))
            threshold = thresholds[i]
            st["over"] = st["over"] + 1 if value > threshold else 0
            st["under"] = st["under"] + 1 if value < rules.clear_level(rule.params, threshold) else 0
            st["last"], st["value"], st["threshold"] = int(steps[j]), value, threshold
            over, under = st["over"] >= debounce, st["under"] >= debounce
            st["is_under"] = under
            beyond = i >= rule.calibrated_decisions
            ep.beyond_calibration = ep.beyond_calibration or beyond
            st["flags"][str(int(steps[j]))] = over
            out.append((int(steps[j]), signal, over, under, value, threshold, beyond))
        if len(st["flags"]) > FLAGS_KEPT:
            st["flags"] = dict(sorted(st["flags"].items(), key=lambda kv: int(kv[0]))[-FLAGS_KEPT:])
        state[signal] = st
        return out

    @staticmethod
    def _count_to(ep: EpisodeState, signal: str, step: int) -> int:
        """How many values of ``signal`` the episode had up to decision ``step``."""
        return bisect_right(ep.values(signal), (step, float("inf")))

    def flag_unpromised(self, cur, ep: EpisodeState) -> None:
        """At the episode's end: when no false-alert promise covers its final length, its alerts say so."""
        _, detector, _ = self.usable_detector(cur, ep)
        if detector is None:
            return
        why = detector.unpromised_at_end({s: len(ep.values(s)) for s in detector.spec.signals})
        if why:
            statements.flag_unpromised(self.sql, cur, ep.id, why)

    def _judge(self, cur, req: Request, ep: EpisodeState, state: dict, detector: CalibratedDetector,
               cal_id: int, step: int, signal: str, over: bool, under: bool, value: float, threshold: float,
               beyond: bool) -> None:
        """The detector's raise or clear after one signal's value at ``step``. A raised alert says at once when no
        false-alert promise can cover it (the episode has run past every promised length: ``no_promise``);
        ``flag_unpromised`` says it at the episode's end when its final length has none."""
        spec = detector.spec
        if ep.open_alert_id is None:
            if not over:
                return
            raised_by = [signal]
            if spec.combination == "fiper":
                partner = next(s for s in spec.signals if s != signal)
                if not state.get(partner, {}).get("flags", {}).get(str(step), False):
                    return
                raised_by = list(spec.signals)
            unpromised = detector.unpromised_now({s: self._count_to(ep, s, step) for s in spec.signals})
            note = f"{spec.name}: {'+'.join(raised_by)} over the threshold" + (
                f"; beyond the {detector.rules[signal].calibrated_decisions} calibrated decisions of {signal}: no "
                "false-alert guarantee covers it" if beyond else "") + (f"; {unpromised}" if unpromised else "")
            ep.open_alert_id = statements.insert_alert(self.sql, cur, ep, cal_id, step, value, threshold, note, beyond,
                                                       self.settings.webhook_urls, ",".join(raised_by),
                                                       no_promise=bool(unpromised))
            req.alerts_raised.append(ep.open_alert_id)
            req.observations.append(("alert", ep.task, ep.robot, 1.0))
            req.signal_observations += [("alert", ep.task, ep.robot, s, 1.0) for s in raised_by]
        elif under and all(state.get(s, {}).get("is_under", True) for s in spec.signals):
            statements.clear_alert(self.sql, cur, ep.open_alert_id)
            ep.open_alert_id = None
