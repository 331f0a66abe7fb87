"""What the calibration and report endpoints and the CLI do with the database (the ingest path is ingest.py)."""
from __future__ import annotations

import numpy as np
from sqlalchemy import select, update
from sqlalchemy.orm import Session

from monitor_service import calibration, stats
from monitor_service.db import CalibrationRow, Episode, Task, read_decisions
from monitor_service.signals import SERVICE_SIGNALS
from monitor_service.ingest import rule_params
from monitor_service.settings import MonitorSettings


def active_calibration(session: Session, task: str, checkpoint: str | None) -> CalibrationRow | None:
    """The checkpoint's own active calibration when there is one, else the task's."""
    if checkpoint is not None:
        row = session.scalar(
            select(CalibrationRow).where(
                CalibrationRow.task == task, CalibrationRow.checkpoint == checkpoint, CalibrationRow.active.is_(True)
            )
        )
        if row is not None:
            return row
    return session.scalar(
        select(CalibrationRow).where(
            CalibrationRow.task == task, CalibrationRow.checkpoint.is_(None), CalibrationRow.active.is_(True)
        )
    )


def calibration_data(session: Session, task: str, checkpoint: str | None) -> list[calibration.LabelledEpisode]:
    """A task's held-out labelled episodes (optionally of one checkpoint) with every decision, in two queries."""
    q = select(Episode).where(Episode.task == task, Episode.held_out.is_(True), Episode.success.is_not(None))
    if checkpoint is not None:
        q = q.where(Episode.checkpoint == checkpoint)
    eps = {e.id: calibration.LabelledEpisode(e.id, bool(e.success), [], e.group, e.length)
           for e in session.scalars(q.order_by(Episode.id))}
    for episode_id, decisions in read_decisions(session, list(eps)).items():
        eps[episode_id].decisions.extend(decisions)
    return list(eps.values())


def calibrate_task(
    make_session, settings: MonitorSettings, task: str, checkpoint: str | None = None, alpha: float | None = None,
    rule: str | None = None, n_bootstrap: int | None = None, n_permutation: int | None = None,
    seed: int | None = None, folds: int | None = None, shape: str | None = None,
    signals: list[str] | None = None, combination: str | None = None,
) -> CalibrationRow:
    """Calibrate one task (optionally one checkpoint) from its held-out episodes and make it the active one.

    The alert rule is the service's (window, debounce, hysteresis) with ``rule`` or the settings' kind; the
    detector alerts on ``signals`` (default nmse) combined by ``combination`` (default single).
    Raises LookupError for an unknown task or a signal it does not have, ValueError when the data (or the
    combination) cannot support a calibration.
    """
    alpha = settings.alpha if alpha is None else alpha
    params = rule_params(settings, rule, shape)
    signals = list(dict.fromkeys(signals or ["nmse"]))
    with make_session() as session:
        row = session.get(Task, task)
        if row is None:
            raise LookupError(f"task {task!r} is not registered; register it with PUT /v1/tasks/{task}")
        unknown = [s for s in signals if s not in SERVICE_SIGNALS and s not in (row.signals or [])]
        if "nmse_persistence" in unknown:   # a reserved name: registering it is refused, so do not suggest that
            raise LookupError("nmse_persistence is the persistence control (NMSE of z_now against the target), "
                              "reported under the calibration's controls, not a signal to alert on; calibrate "
                              "nmse_ratio (NMSE over it) or nmse")
        if unknown:
            raise LookupError(f"task {task!r} has no signal {unknown[0]!r} (its signals: nmse, nmse_ratio"
                              + "".join(f", {s}" for s in row.signals or []) + f"); register it with PUT /v1/tasks/"
                              f"{task} {{\"signals\": [\"{unknown[0]}\"]}} and send it on held-out episodes")
        episodes = calibration_data(session, task, checkpoint)
        session.rollback()  # release the database while the resampling runs
    result = calibration.calibrate(
        episodes, params, alpha, folds=settings.detection_folds if folds is None else folds,
        early_decisions=settings.early_decisions,
        n_bootstrap=settings.n_bootstrap if n_bootstrap is None else n_bootstrap,
        n_permutation=settings.n_permutation if n_permutation is None else n_permutation,
        seed=settings.stats_seed if seed is None else seed, signals=tuple(signals),
        combination=combination or ("single" if len(signals) == 1 else "bonferroni"),
    )
    with make_session() as session:
        cond = CalibrationRow.checkpoint.is_(None) if checkpoint is None else CalibrationRow.checkpoint == checkpoint
        session.execute(update(CalibrationRow).where(CalibrationRow.task == task, cond).values(active=False))
        row = CalibrationRow(task=task, checkpoint=checkpoint, active=True, rule=params.kind,
                             threshold=result["rule"]["threshold"], auroc=result["auroc"], result=result)
        session.add(row)
        session.commit()
        return row


POOLED_WARNING = (
    "WARNING: pooled across tasks. Raw NMSE scales differ per task, so pooled scores can rank failures at "
    "chance even when every task's own calibration ranks them well (Simpson-type effect, paper Sec. 4.10). "
    "Never threshold on this figure; use the per-task calibrations."
)


def report(session: Session) -> dict:
    """Per-task active calibrations, the uncalibrated tasks, and the pooled AUROC shown only as a warning."""
    rows = session.scalars(
        select(CalibrationRow).where(CalibrationRow.active.is_(True)).order_by(CalibrationRow.task, CalibrationRow.id)
    ).all()
    calibrated = {r.task for r in rows}
    tasks = session.scalars(select(Task.name).order_by(Task.name)).all()
    held = session.execute(select(Episode.early_score, Episode.success).where(
        Episode.held_out.is_(True), Episode.success.is_not(None), Episode.early_score.is_not(None))).all()
    scores = np.array([r.early_score for r in held], dtype=np.float64)
    labels = np.array([0 if r.success else 1 for r in held], dtype=np.int64)
    pooled = None
    if labels.size and 0 < labels.sum() < labels.size:
        pooled = stats.auroc(scores, labels)
    return {
        "tasks": rows,
        "uncalibrated_tasks": [t for t in tasks if t not in calibrated],
        "pooled": {"warning": POOLED_WARNING, "auroc": pooled, "n_episodes": int(labels.size)},
    }
