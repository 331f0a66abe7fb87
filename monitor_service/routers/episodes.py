"""Episodes: live and finished, with their early and running scores and why they can or cannot alert."""
from __future__ import annotations

import datetime as dt

from fastapi import APIRouter, Depends, HTTPException, Query
from sqlalchemy import select
from sqlalchemy.orm import Session

from monitor_service import scoring
from monitor_service.auth import Principal, require
from monitor_service.db import Episode, read_decisions, utcnow
from monitor_service.deps import get_read_session, get_settings
from monitor_service.calibration import LabelledEpisode
from monitor_service.ingest.alerting import stored_detector
from monitor_service.schemas import DecisionOut, EpisodeDetail, EpisodeOut, RiskPoint, errors
from monitor_service.service import active_calibration, rule_params
from monitor_service.settings import MonitorSettings

router = APIRouter(prefix="/v1/episodes", tags=["episodes"])


def episode_out(e: Episode, live_s: float) -> dict:
    live = e.success is None and (utcnow() - e.updated_at) < dt.timedelta(seconds=live_s)
    return dict(
        id=e.id, task=e.task, robot=e.robot, checkpoint=e.checkpoint, group=e.group, held_out=e.held_out,
        success=e.success, early_score=e.early_score, early_revisions=e.early_revisions,
        running_score=e.running_score, risk_score=e.risk_score, risk_threshold=e.risk_threshold,
        calibrated_decisions=e.calibrated_decisions, beyond_calibration=e.beyond_calibration, gaps=e.gaps,
        gap_steps=e.gap_steps or [], late_decisions=e.late_decisions, length=e.length, n_decisions=e.n_decisions,
        n_scored=e.n_scored, open_alert_id=e.open_alert_id, alert_note=e.alert_note, live=live,
        started_at=e.started_at, updated_at=e.updated_at,
    )


@router.get("", response_model=list[EpisodeOut])
def list_episodes(
    task: str | None = None,
    live: bool | None = Query(None, description="only live (true) or only ended/stale (false) episodes"),
    limit: int = Query(100, ge=1, le=5000),
    session: Session = Depends(get_read_session),
    settings: MonitorSettings = Depends(get_settings),
    _: Principal = Depends(require("operator")),
) -> list[EpisodeOut]:
    """Most recently active episodes first."""
    q = select(Episode).order_by(Episode.updated_at.desc(), Episode.id)
    if task:
        q = q.where(Episode.task == task)
    if live is not None:
        cutoff = utcnow() - dt.timedelta(seconds=settings.live_episode_s)
        cond = Episode.success.is_(None) & (Episode.updated_at >= cutoff)
        q = q.where(cond if live else ~cond)
    return [EpisodeOut(**episode_out(e, settings.live_episode_s)) for e in session.scalars(q.limit(limit))]


@router.get("/{episode_id}", response_model=EpisodeDetail, responses=errors(404))
def get_episode(
    episode_id: str,
    session: Session = Depends(get_read_session),
    settings: MonitorSettings = Depends(get_settings),
    _: Principal = Depends(require("operator")),
) -> EpisodeDetail:
    """One episode with every decision's NMSE (null until its realized target arrives) and, when its task has a
    usable calibration, the alert rule's statistic over the episode against the rule's threshold."""
    e = session.get(Episode, episode_id)
    if e is None:
        raise HTTPException(404, f"episode {episode_id!r} is unknown; list episodes with GET /v1/episodes")
    decisions = read_decisions(session, [e.id])[e.id]
    detector = None
    cal = active_calibration(session, e.task, e.checkpoint)
    if cal is not None and {"shape", "unpromised_lengths"} <= set(cal.result.get("rule", {})):
        candidate = stored_detector(cal.result)
        made = candidate.spec.params
        if made == rule_params(settings, made.kind, made.shape):
            detector = candidate
    signal_risk = {}
    if detector is not None:
        episode = LabelledEpisode(e.id, bool(e.success), decisions, e.group, e.length).signal_episode()
        for signal, flags in detector.flags(episode).items():
            rule = detector.rules[signal]
            signal_risk[signal] = [
                RiskPoint(step=int(s), known_at=int(k), value=float(v), threshold=float(t),
                          beyond_calibration=i >= rule.calibrated_decisions)
                for i, (s, k, v, t) in enumerate(zip(flags.steps, flags.known_at, flags.values, flags.thresholds))]
    first = None if detector is None else detector.spec.signals[0]
    return EpisodeDetail(
        **episode_out(e, settings.live_episode_s),
        decisions=[DecisionOut(**d, nmse_ratio=scoring.nmse_ratio_or_none(d["nmse"], d["nmse_persistence"]))
                   for d in decisions],
        rule=None if detector is None else detector.spec.params.kind,
        detector=None if detector is None else detector.spec.name,
        threshold=None if detector is None else detector.rules[first].threshold,
        risk=signal_risk.get(first, []), signal_risk=signal_risk,
    )
