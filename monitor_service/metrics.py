"""Prometheus metrics. Labels are bounded: task and robot only, never an episode id.

With several workers set PROMETHEUS_MULTIPROC_DIR (``jepa-monitor serve --workers N`` does it): counters and
histograms then aggregate across processes. Per-task gauges (AUROC, threshold, open alerts) are read from the
database at scrape time, so every worker reports the same committed truth.
"""
from __future__ import annotations

import os
from bisect import bisect_left

from prometheus_client import CollectorRegistry, Counter, Histogram, generate_latest
from prometheus_client.core import GaugeMetricFamily
from prometheus_client.multiprocess import MultiProcessCollector
from sqlalchemy import distinct, func, select
from sqlalchemy.orm import sessionmaker

from monitor_service.db import Alert, CalibrationRow, Episode

NMSE_BUCKETS = (0.01, 0.02, 0.05, 0.1, 0.2, 0.3, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 5.0, 10.0, 20.0, 50.0)
LATENCY_BUCKETS = (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0)

NMSE = Histogram("jepa_monitor_nmse", "Per-decision future-consistency NMSE (Sec. 3.6)", ["task", "robot"],
                 buckets=NMSE_BUCKETS)
REQUEST_SECONDS = Histogram("jepa_monitor_request_seconds", "HTTP request latency", buckets=LATENCY_BUCKETS)
DECISIONS = Counter("jepa_monitor_decisions", "Decisions ingested", ["task", "robot"])
TARGETS = Counter("jepa_monitor_targets", "Realized latents ingested", ["task", "robot"])
OUTCOMES = Counter("jepa_monitor_outcomes", "Episode outcomes ingested", ["task", "robot"])
ALERTS = Counter("jepa_monitor_alerts", "Intervention alerts raised", ["task", "robot"])
GAPS = Counter("jepa_monitor_decision_gaps", "Decision indices skipped when a later decision arrived (a lost or "
               "unsent decision; a late one may fill it)", ["task", "robot"])
LATE = Counter("jepa_monitor_late_decisions", "Decisions that arrived after a later decision of their episode",
               ["task", "robot"])
WEBHOOK_FAILURES = Counter("jepa_monitor_webhook_failures", "Failed webhook delivery attempts")
SCORE_BUCKETS = (0.001, 0.003, 0.01, 0.03, 0.1, 0.3, 1.0, 3.0, 10.0, 30.0, 100.0, 300.0, 1000.0)
SCORES = Histogram("jepa_monitor_score", "Named per-decision scores sent beside the latents, and the service's "
                   "nmse_ratio (per signal)",
                   ["task", "robot", "signal"], buckets=SCORE_BUCKETS)
SIGNAL_ALERTS = Counter("jepa_monitor_signal_alerts", "Alerts raised, per signal that raised them", ["task", "signal"])


def observe_many(histogram, values: list[float]) -> None:
    """``histogram.observe(v)`` for every value of ``values`` (a labelled child), as one increment of the sum and
    one per bucket touched: prometheus_client keeps each bucket's own count (``_buckets``, made cumulative when
    collected) and ``observe`` walks the bounds once per value, the larger part of publishing a batch."""
    bounds = histogram._upper_bounds
    counts: dict[int, int] = {}
    for value in values:
        i = bisect_left(bounds, value)   # the first bound >= value: observe's bucket
        counts[i] = counts.get(i, 0) + 1
    histogram._sum.inc(sum(values))
    for i, n in counts.items():
        histogram._buckets[i].inc(n)


def publish(observations: list[tuple[str, str, str, float]],
            signal_observations: list[tuple[str, str, str, str, float]] = ()) -> None:
    """Turn a committed request's (kind, task, robot, value) and (kind, task, robot, signal, value) observations
    into Prometheus samples. Signals are the task's registered names: bounded like tasks."""
    scores: dict[tuple[str, str, str], list[float]] = {}
    for kind, task, robot, signal, value in signal_observations:
        if kind == "score":
            scores.setdefault((task, robot, signal), []).append(value)
        else:
            SIGNAL_ALERTS.labels(task, signal).inc()
    for labels, values in scores.items():
        observe_many(SCORES.labels(*labels), values)
    counters = {"decision": DECISIONS, "target": TARGETS, "outcome": OUTCOMES, "alert": ALERTS, "gap": GAPS,
                "late": LATE}
    counts: dict[tuple[str, str, str], float] = {}
    nmse: dict[tuple[str, str], list[float]] = {}
    for kind, task, robot, value in observations:
        if kind == "nmse":
            values = nmse.get((task, robot))
            if values is None:
                values = nmse[task, robot] = []
            values.append(value)
        else:
            counts[kind, task, robot] = counts.get((kind, task, robot), 0.0) + value
    for labels, values in nmse.items():   # one labelled child per (task, robot) of the request
        observe_many(NMSE.labels(*labels), values)
    for (kind, task, robot), total in counts.items():   # a batch's records: one increment per counter
        counters[kind].labels(task, robot).inc(total)


class DatabaseGauges:
    """Custom collector: per-task calibration gauges, open alerts and live alert rates, queried at scrape time.

    ``rule_params`` is the alert rule the service runs (window, debounce, clear ratio); a calibration made for
    other values is reported stale (it raises no alerts until recalibrated).
    """

    def __init__(self, make_session: sessionmaker, rule_params: tuple[int, int, float] | None = None):
        self.make_session = make_session
        self.rule_params = rule_params

    def collect(self):
        auroc = GaugeMetricFamily("jepa_monitor_task_auroc", "AUROC of the active task calibration", labels=["task"])
        thr = GaugeMetricFamily(
            "jepa_monitor_task_threshold", "Active alarm threshold (+Inf: too few successes)", labels=["task"]
        )
        open_alerts = GaugeMetricFamily("jepa_monitor_open_alerts", "Alerts raised, neither cleared nor resolved by "
                                        "their episode's outcome (open or acknowledged)", labels=["task"])
        target = GaugeMetricFamily(
            "jepa_monitor_calibration_false_alert_target",
            "Calibrated bound on the share of successful episodes that raise any alert (alpha)",
            labels=["task", "checkpoint", "rule"])
        stale = GaugeMetricFamily(
            "jepa_monitor_calibration_stale",
            "1 when the active calibration was made for another window/debounce/hysteresis (no alerts)",
            labels=["task", "checkpoint"])
        live_rate = GaugeMetricFamily(
            "jepa_monitor_task_live_alert_rate", "Share of live (not held-out) episodes that raised an alert",
            labels=["task"])
        live_false = GaugeMetricFamily(
            "jepa_monitor_task_live_false_alert_rate",
            "Share of live successful episodes that raised an alert (compare with the false-alert target)",
            labels=["task"])
        signal_threshold = GaugeMetricFamily(
            "jepa_monitor_signal_threshold",
            "Active calibration's threshold per signal at its longest calibrated decision index", labels=["task",
                                                                                                          "checkpoint",
                                                                                                          "signal"])
        alerting = GaugeMetricFamily(
            "jepa_monitor_signal_alerting", "1 for the signals of the active calibration's detector",
            labels=["task", "checkpoint", "signal"])
        with self.make_session() as session:
            rows = session.scalars(
                select(CalibrationRow).where(CalibrationRow.active.is_(True), CalibrationRow.checkpoint.is_(None))
            ).all()
            for row in rows:
                auroc.add_metric([row.task], row.auroc)
                thr.add_metric([row.task], row.threshold if row.threshold is not None else float("inf"))
            for row in session.scalars(select(CalibrationRow).where(CalibrationRow.active.is_(True))):
                rule = row.result.get("rule")   # None: made before episode-level rules existed, raises no alert
                labels = [row.task, row.checkpoint or ""]
                if rule is not None:
                    target.add_metric([*labels, row.rule], float(rule["alpha"]))
                for signal, data in row.result.get("signals", {}).items():
                    if data.get("rule") is not None:
                        signal_threshold.add_metric([*labels, signal], float(data["rule"]["threshold"]))
                spec = (row.result.get("detector") or {}).get("spec", {})
                for signal in spec.get("signals", ["nmse"] if rule else []):
                    alerting.add_metric([*labels, signal], 1.0)
                if self.rule_params is not None:
                    params = (rule or {}).get("params", {})
                    made_for = (params.get("window"), params.get("debounce"), params.get("clear_ratio"))
                    stale.add_metric(labels, float(made_for != self.rule_params or "shape" not in (rule or {})
                                                        or "unpromised_lengths" not in (rule or {})))
            live = Episode.held_out.is_(False)
            episodes = dict(session.execute(
                select(Episode.task, func.count()).where(live).group_by(Episode.task)).all())
            alerted = dict(session.execute(
                select(Episode.task, func.count(distinct(Alert.episode_id))).join(Alert, Alert.episode_id == Episode.id)
                .where(live).group_by(Episode.task)).all())
            successes = dict(session.execute(select(Episode.task, func.count()).where(
                live, Episode.success.is_(True)).group_by(Episode.task)).all())
            alerted_successes = dict(session.execute(
                select(Episode.task, func.count(distinct(Alert.episode_id))).join(Alert, Alert.episode_id == Episode.id)
                .where(live, Episode.success.is_(True)).group_by(Episode.task)).all())
            for task, n in episodes.items():
                live_rate.add_metric([task], alerted.get(task, 0) / n)
            for task, n in successes.items():
                live_false.add_metric([task], alerted_successes.get(task, 0) / n)
            for task, n in session.execute(
                select(Alert.task, func.count()).where(Alert.state.in_(("open", "acknowledged"))).group_by(Alert.task)
            ):
                open_alerts.add_metric([task], n)
            session.rollback()
        yield from (auroc, thr, open_alerts, target, stale, live_rate, live_false, signal_threshold, alerting)


def exposition(make_session: sessionmaker, rule_params: tuple[int, int, float] | None = None) -> bytes:
    """The /metrics body: process metrics (aggregated across workers in multiprocess mode) plus database gauges."""
    from prometheus_client import REGISTRY

    db_registry = CollectorRegistry()
    db_registry.register(DatabaseGauges(make_session, rule_params))
    if os.environ.get("PROMETHEUS_MULTIPROC_DIR"):
        registry = CollectorRegistry()
        MultiProcessCollector(registry)
        return generate_latest(registry) + generate_latest(db_registry)
    return generate_latest(REGISTRY) + generate_latest(db_registry)
