"""Prometheus metrics. Labels are bounded: task and robot only, never an episode id.

With several workers set PROMETHEUS_MULTIPROC_DIR (``jepa-monitor serve --workers N`` does it): counters and
histograms then aggregate across processes. Per-task gauges (AUROC, threshold, open alerts) are read from the
database at scrape time, so every worker reports the same committed truth.
"""
from __future__ import annotations

import os

from prometheus_client import CollectorRegistry, Counter, Histogram, generate_latest
from prometheus_client.core import GaugeMetricFamily
from prometheus_client.multiprocess import MultiProcessCollector
from sqlalchemy import func, select
from sqlalchemy.orm import sessionmaker

from monitor_service.db import Alert, CalibrationRow

NMSE_BUCKETS = (0.01, 0.02, 0.05, 0.1, 0.2, 0.3, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 5.0, 10.0, 20.0, 50.0)
LATENCY_BUCKETS = (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0)

NMSE = Histogram("jepa_monitor_nmse", "Per-decision future-consistency NMSE (Sec. 3.6)", ["task", "robot"], buckets=NMSE_BUCKETS)
REQUEST_SECONDS = Histogram("jepa_monitor_request_seconds", "HTTP request latency", buckets=LATENCY_BUCKETS)
DECISIONS = Counter("jepa_monitor_decisions", "Decisions ingested", ["task", "robot"])
TARGETS = Counter("jepa_monitor_targets", "Realized latents ingested", ["task", "robot"])
OUTCOMES = Counter("jepa_monitor_outcomes", "Episode outcomes ingested", ["task", "robot"])
ALERTS = Counter("jepa_monitor_alerts", "Intervention alerts raised", ["task", "robot"])
WEBHOOK_FAILURES = Counter("jepa_monitor_webhook_failures", "Failed webhook delivery attempts")


class DatabaseGauges:
    """Custom collector: per-task calibration gauges and open alerts, queried at scrape time."""

    def __init__(self, make_session: sessionmaker):
        self.make_session = make_session

    def collect(self):
        auroc = GaugeMetricFamily("jepa_monitor_task_auroc", "AUROC of the active task calibration", labels=["task"])
        thr = GaugeMetricFamily(
            "jepa_monitor_task_threshold", "Active alarm threshold (+Inf: too few successes)", labels=["task"]
        )
        open_alerts = GaugeMetricFamily("jepa_monitor_open_alerts", "Alerts raised and not yet cleared", labels=["task"])
        with self.make_session() as session:
            rows = session.scalars(
                select(CalibrationRow).where(CalibrationRow.active.is_(True), CalibrationRow.checkpoint.is_(None))
            ).all()
            for row in rows:
                auroc.add_metric([row.task], row.auroc)
                thr.add_metric([row.task], row.threshold if row.threshold is not None else float("inf"))
            for task, n in session.execute(
                select(Alert.task, func.count()).where(Alert.state == "open").group_by(Alert.task)
            ):
                open_alerts.add_metric([task], n)
            session.rollback()
        yield from (auroc, thr, open_alerts)


def exposition(make_session: sessionmaker) -> bytes:
    """The /metrics body: process metrics (aggregated across workers in multiprocess mode) plus database gauges."""
    from prometheus_client import REGISTRY

    db_registry = CollectorRegistry()
    db_registry.register(DatabaseGauges(make_session))
    if os.environ.get("PROMETHEUS_MULTIPROC_DIR"):
        registry = CollectorRegistry()
        MultiProcessCollector(registry)
        return generate_latest(registry) + generate_latest(db_registry)
    return generate_latest(REGISTRY) + generate_latest(db_registry)
