"""Per episode after its records are applied: the early and running scores, and the calibrated alert rule
stepped over the decisions scored since the last evaluation (``rules.py`` is the same rule, offline)."""
from __future__ import annotations

import statistics
import time
from bisect import bisect_right

import numpy as np

from monitor_service import rules, scoring
from monitor_service.alerts import AlertState, step_alert
from monitor_service.ingest import sql as statements
from monitor_service.ingest.sql import Sql
from monitor_service.ingest.state import EpisodeState, Request
from monitor_service.settings import MonitorSettings

CALIBRATION_TTL_S = 1.0      # another process's new calibration is seen within this time


def rule_params(settings: MonitorSettings, kind: str | None = None, shape: str | None = None) -> rules.RuleParams:
    """The alert rule the service runs now: window, debounce and hysteresis from the settings; kind and threshold
    shape the calibration's (or the settings' for a new one)."""
    return rules.RuleParams(kind or settings.alert_rule, settings.running_window, settings.alert_debounce,
                            settings.alert_clear_ratio, shape or settings.threshold_shape)


class Alerting:
    """The active calibrations' rules (cached briefly) and their evaluation over an episode's new scores."""

    def __init__(self, sql: Sql, settings: MonitorSettings):
        self.sql = sql
        self.settings = settings
        self.calibrations: dict[tuple[str, str | None], tuple[float, tuple[int | None, dict | None]]] = {}
        self.rules: dict[int, rules.CalibratedRule] = {}

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

    def usable_rule(self, cur, ep: EpisodeState) -> tuple[int | None, rules.CalibratedRule | None, str]:
        """(calibration id, its rule or None when it cannot alert, the episode's alert note saying why)."""
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
        if cal_id not in self.rules:
            self.rules[cal_id] = rules.CalibratedRule.from_dict(result["rule"])
        rule = self.rules[cal_id]
        now = rule_params(self.settings, rule.params.kind, rule.params.shape)
        if rule.params != now:
            return cal_id, None, (
                f"no alerts: calibration #{cal_id} holds for window={rule.params.window}, "
                f"debounce={rule.params.debounce}, clear ratio={rule.params.clear_ratio}, but the service runs "
                f"window={now.window}, debounce={now.debounce}, clear ratio={now.clear_ratio}; its false-alert "
                f"guarantee does not cover that rule, so recalibrate with {fix}")
        return cal_id, rule, (
            f"alerting when {rule.params.debounce} consecutive values of the {rule.params.kind} statistic (median "
            f"of {rule.params.window}) exceed their decision's threshold (up to {rule.threshold:.6g}): calibration "
            f"#{cal_id}, at most {rule.alpha:g} of successful episodes alert in each length regime up to "
            f"{rule.calibrated_decisions} scored decisions")

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
        """Early score, running NMSE, and the alert rule over the decisions scored since the last evaluated step,
        in step order, each judged against its index's threshold. A decision scored after a later one was
        evaluated counts for the scores but is not evaluated for alerts."""
        settings = self.settings
        self.early_score(ep)
        ep.n_scored += req.newly_scored.get(ep.id, 0)
        running = scoring.running_score([v for _, v in ep.scored], settings.running_window)
        if running is not None:
            ep.running_score = running
        first_new = bisect_right(ep.scored, (ep.last_evaluated_step, float("inf")))
        todo = range(first_new, len(ep.scored))
        if not todo:
            return
        cal_id, rule, ep.alert_note = self.usable_rule(cur, ep)
        if rule is None:
            ep.last_evaluated_step = ep.scored[-1][0]
            ep.risk_threshold = ep.calibrated_decisions = None
            return
        window = rule.params.window
        lo = max(0, todo[0] + 1 - window)
        part = ep.scored[lo:]
        steps = np.array([s for s, _ in part], dtype=np.int64)
        values = rules.decision_values(rule.params, rules.EpisodeScores(steps, np.array([v for _, v in part]), steps),
                                       rule.band).tolist()
        thresholds = rule.thresholds(len(ep.scored)).tolist()
        ep.calibrated_decisions = rule.calibrated_decisions
        state = AlertState(ep.over_count, ep.under_count, ep.open_alert_id is not None)
        for i in todo:
            j = i - lo
            step = int(steps[j])
            ep.last_evaluated_step = step
            value = float(statistics.median(values[max(0, j + 1 - window): j + 1]))
            threshold = thresholds[i]
            beyond = i >= rule.calibrated_decisions
            ep.risk_score, ep.risk_threshold = value, threshold
            ep.beyond_calibration = ep.beyond_calibration or beyond
            state, event = step_alert(state, value, threshold, rule.params.debounce,
                                      rules.clear_level(rule.params, threshold))
            if event == "raise":
                note = f"{rule.params.kind} rule" + (
                    f"; decision index {i} lies beyond the {rule.calibrated_decisions} calibrated decisions: no "
                    "false-alert guarantee covers it" if beyond else "")
                ep.open_alert_id = statements.insert_alert(self.sql, cur, ep, cal_id, step, value, threshold,
                                                           note, beyond, self.settings.webhook_urls)
                req.alerts_raised.append(ep.open_alert_id)
                req.observations.append(("alert", ep.task, ep.robot, 1.0))
            elif event == "clear":
                statements.clear_alert(self.sql, cur, ep.open_alert_id)
                ep.open_alert_id = None
        ep.over_count, ep.under_count = state.over, state.under
