"""What the endpoints and the CLI do with the database: ingest, score, alert, calibrate, report.

Ingestion applies a request's records in order inside the caller's transaction; any bad record raises
:class:`IngestError` and the caller rolls back, so nothing already accepted is lost or changed.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from sqlalchemy import insert, select, update
from sqlalchemy.orm import Session

from monitor_service import calibration, metrics, rules, scoring, stats
from monitor_service.alerts import AlertState, step_alert
from monitor_service.auth import Principal
from monitor_service.db import Alert, CalibrationRow, Decision, Episode, Target, Task, WebhookDelivery, utcnow
from monitor_service.schemas import DecisionIn, OutcomeIn, TargetIn
from monitor_service.settings import MonitorSettings


class IngestError(Exception):
    """A record the service refuses; ``status`` is the HTTP status, the message names problem and fix."""

    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status = status
        self.message = message


@dataclass
class _Dec:
    """A decision known to this request: loaded from the database (``id`` set) or new in it."""

    episode: str
    step: int
    horizon: int
    z_hat: bytes
    nmse: float | None
    id: int | None = None
    changed: bool = False
    z_now: bytes | None = None
    nmse_persistence: float | None = None


@dataclass
class IngestContext:
    """Per-request state: what the batch touches, preloaded in a few queries, and what to write back.

    Records are checked and scored in memory, then written with bulk statements; side effects to publish after
    commit (metrics samples, raised alert ids) are collected here.
    """

    session: Session
    principal: Principal
    settings: MonitorSettings
    # Latent sizes of tasks, shared by the app across requests (a committed latent_dim never changes).
    known_dims: dict[str, int] = field(default_factory=dict)
    tasks: dict[str, Task] = field(default_factory=dict)
    episodes: dict[str, Episode] = field(default_factory=dict)
    decisions: dict[tuple[str, int], _Dec] = field(default_factory=dict)
    aimed_at: dict[tuple[str, int], list[_Dec]] = field(default_factory=dict)
    targets: dict[tuple[str, int], bytes] = field(default_factory=dict)
    new_decisions: list[_Dec] = field(default_factory=list)
    new_targets: list[dict] = field(default_factory=list)
    dirty: dict[str, Episode] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=lambda: {"decision": 0, "target": 0, "outcome": 0})
    # (kind, task, robot, value) tuples turned into Prometheus samples once the transaction committed
    observations: list[tuple[str, str, str, float]] = field(default_factory=list)
    alerts_raised: list[int] = field(default_factory=list)
    calibrations: dict[tuple[str, str | None], CalibrationRow | None] = field(default_factory=dict)
    newly_scored: dict[str, int] = field(default_factory=dict)
    new_decision_episodes: set[str] = field(default_factory=set)
    calibrated_rules: dict[int, rules.CalibratedRule] = field(default_factory=dict)
    scored: int = 0

    def preload(self, records: list) -> None:
        """Load the touched episodes, decisions and realized targets with one query each."""
        s = self.session
        ep_ids = {r.episode for r in records}
        # FOR UPDATE (PostgreSQL): concurrent requests on one episode queue here instead of losing each other's
        # counter and alert-state updates. SQLite ignores it; BEGIN IMMEDIATE already serialises writers there.
        for ep in s.scalars(select(Episode).where(Episode.id.in_(ep_ids)).order_by(Episode.id).with_for_update()):
            self.episodes[ep.id] = ep
        known = [e for e in ep_ids if e in self.episodes]
        if not known:
            return
        steps = {r.step for r in records if r.kind == "decision"}
        tsteps = {r.step + r.horizon for r in records if r.kind == "decision"} | {r.step for r in records if r.kind == "target"}
        cols = (Decision.id, Decision.episode_id, Decision.step, Decision.horizon, Decision.z_hat, Decision.nmse,
                Decision.z_now)
        # Two indexed lookups: decisions at the batch's steps, and decisions aimed at its target steps.
        for cond in (Decision.step.in_(steps), Decision.target_step.in_(tsteps)):
            for r in s.execute(select(*cols).where(Decision.episode_id.in_(known), cond)):
                if (r.episode_id, r.step) not in self.decisions:
                    self._remember(_Dec(r.episode_id, r.step, r.horizon, r.z_hat, r.nmse, r.id, z_now=r.z_now))
        for r in s.execute(
            select(Target.episode_id, Target.step, Target.z).where(Target.episode_id.in_(known), Target.step.in_(tsteps))
        ):
            self.targets[(r.episode_id, r.step)] = r.z

    def _remember(self, d: _Dec) -> None:
        self.decisions[(d.episode, d.step)] = d
        self.aimed_at.setdefault((d.episode, d.step + d.horizon), []).append(d)

    def write(self) -> None:
        """Bulk-insert the new rows and the newly scored NMSE of stored decisions."""
        s = self.session
        if self.new_decisions:
            s.execute(insert(Decision), [
                {"episode_id": d.episode, "step": d.step, "horizon": d.horizon, "target_step": d.step + d.horizon,
                 "z_hat": d.z_hat, "nmse": d.nmse, "z_now": d.z_now, "nmse_persistence": d.nmse_persistence,
                 "created_at": utcnow()} for d in self.new_decisions
            ])
        if self.new_targets:
            s.execute(insert(Target), self.new_targets)
        updates = [{"id": d.id, "nmse": d.nmse, "nmse_persistence": d.nmse_persistence}
                   for d in self.decisions.values() if d.id is not None and d.changed]
        if updates:
            s.execute(update(Decision), updates)


def _check_dim(ctx: IngestContext, name: str, dim: int, what: str) -> None:
    """The task must be registered and ``dim`` must be its latent size (fixed by its first latent if unset)."""
    known = ctx.known_dims.get(name)
    if known is None:
        task = ctx.tasks.get(name) or ctx.session.get(Task, name)
        if task is None:
            raise IngestError(
                404, f"task {name!r} is not registered; an admin registers it with PUT /v1/tasks/{name} "
                f"or `jepa-monitor tasks add {name}`"
            )
        ctx.tasks[name] = task
        if task.latent_dim is None:
            ctx.session.refresh(task, with_for_update=True)  # two first latents must not fix two different sizes
            if task.latent_dim is None:
                task.latent_dim = dim
        else:
            ctx.known_dims[name] = task.latent_dim  # committed and never changes again: safe to share
        known = task.latent_dim
    if known != dim:
        raise IngestError(
            422, f"{what} has {dim} dimensions but task {name!r} uses latents of {known}; send the encoder's full latent"
        )


def _check_owner(ctx: IngestContext, ep: Episode) -> None:
    p = ctx.principal   # a robot key (the ingest routes admit no other role)
    if ep.robot != p.robot:
        raise IngestError(403, f"episode {ep.id!r} belongs to robot {ep.robot!r}; your key writes only for {p.robot!r}")


def _score(ctx: IngestContext, ep: Episode, d: _Dec, z: bytes) -> None:
    target = np.frombuffer(z, dtype="<f4")
    d.nmse = scoring.nmse(np.frombuffer(d.z_hat, dtype="<f4"), target)
    if d.z_now is not None:   # the persistence baseline z_hat = z_t against the same target (Sec. 4.10)
        d.nmse_persistence = scoring.nmse(np.frombuffer(d.z_now, dtype="<f4"), target)
    d.changed = True
    ctx.scored += 1
    ctx.newly_scored[ep.id] = ctx.newly_scored.get(ep.id, 0) + 1
    ctx.observations.append(("nmse", ep.task, ep.robot, d.nmse))


def _ingest_decision(ctx: IngestContext, rec: DecisionIn) -> None:
    _check_dim(ctx, rec.task, rec.z_hat.shape[0], "z_hat")
    if rec.z_now is not None:
        _check_dim(ctx, rec.task, rec.z_now.shape[0], "z_now")
    p = ctx.principal   # a robot key, bound to its robot
    robot = rec.robot or p.robot
    if robot != p.robot:
        raise IngestError(403, f"your key writes only for robot {p.robot!r}, not {robot!r}")
    ep = ctx.episodes.get(rec.episode)
    if ep is None:
        ep = Episode(
            id=rec.episode, task=rec.task, robot=robot, checkpoint=rec.checkpoint, group=rec.group,
            held_out=rec.held_out, n_decisions=0, n_scored=0, last_evaluated_step=-1, over_count=0,
            under_count=0, alert_note="", started_at=utcnow(),
        )
        ctx.session.add(ep)
        ctx.episodes[ep.id] = ep
    else:
        _check_owner(ctx, ep)
        if ep.task != rec.task or ep.robot != robot:
            raise IngestError(
                409, f"episode {ep.id!r} is task {ep.task!r} on robot {ep.robot!r}; episode ids must be unique"
            )
        if ep.success is not None:
            raise IngestError(409, f"episode {ep.id!r} has ended (outcome recorded); start a new episode id")
    z_hat = rec.z_hat.astype("<f4").tobytes()
    z_now = None if rec.z_now is None else rec.z_now.astype("<f4").tobytes()
    existing = ctx.decisions.get((ep.id, rec.step))
    if existing is not None:
        if existing.z_hat == z_hat and existing.horizon == rec.horizon:
            return  # the same record again: nothing to change, nothing double-counted
        raise IngestError(409, f"episode {ep.id!r} already has a different decision at step {rec.step}")
    d = _Dec(ep.id, rec.step, rec.horizon, z_hat, None, z_now=z_now)
    target = ctx.targets.get((ep.id, rec.step + rec.horizon))
    if target is not None:
        _score(ctx, ep, d, target)
    ctx._remember(d)
    ctx.new_decisions.append(d)
    ctx.new_decision_episodes.add(ep.id)
    ep.n_decisions += 1
    ep.updated_at = utcnow()
    ctx.dirty[ep.id] = ep
    ctx.counts["decision"] += 1
    ctx.observations.append(("decision", ep.task, ep.robot, 1.0))


def _known_episode(ctx: IngestContext, episode_id: str, what: str) -> Episode:
    ep = ctx.episodes.get(episode_id)
    if ep is None:
        raise IngestError(404, f"episode {episode_id!r} is unknown; send its first decision before its {what}")
    _check_owner(ctx, ep)
    return ep


def _ingest_target(ctx: IngestContext, rec: TargetIn) -> None:
    ep = _known_episode(ctx, rec.episode, "targets")
    _check_dim(ctx, ep.task, rec.z.shape[0], "z")
    z = rec.z.astype("<f4").tobytes()
    existing = ctx.targets.get((ep.id, rec.step))
    if existing is not None:
        if existing == z:
            return
        raise IngestError(409, f"episode {ep.id!r} already has a different realized latent at step {rec.step}")
    ctx.targets[(ep.id, rec.step)] = z
    ctx.new_targets.append({"episode_id": ep.id, "step": rec.step, "z": z, "created_at": utcnow()})
    for d in ctx.aimed_at.get((ep.id, rec.step), []):
        if d.nmse is None:
            _score(ctx, ep, d, z)
    ep.updated_at = utcnow()
    ctx.dirty[ep.id] = ep
    ctx.counts["target"] += 1
    ctx.observations.append(("target", ep.task, ep.robot, 1.0))


def _ingest_outcome(ctx: IngestContext, rec: OutcomeIn) -> None:
    ep = _known_episode(ctx, rec.episode, "outcome")
    if ep.success is not None:
        if ep.success == rec.success:
            return
        raise IngestError(409, f"episode {ep.id!r} already has outcome success={ep.success}; outcomes are final")
    ep.success = rec.success
    if rec.held_out is not None:
        ep.held_out = rec.held_out
    if rec.group is not None:
        ep.group = rec.group
    if rec.length is not None:
        ep.length = rec.length
    ep.ended_at = ep.updated_at = utcnow()
    ctx.dirty[ep.id] = ep
    ctx.counts["outcome"] += 1
    ctx.observations.append(("outcome", ep.task, ep.robot, 1.0))


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


def _history(s: Session, ep: Episode, settings: MonitorSettings, early: bool) -> tuple[list, list]:
    """What a refresh needs, in bounded queries: the first decisions by step (when ``early``: the early score is
    not fixed yet, or an earlier decision may have arrived) and the scored decisions after the last evaluated
    step, preceded by the window of scored ones before it."""
    first = []
    if early:
        first = s.execute(
            select(Decision.step, Decision.nmse).where(Decision.episode_id == ep.id)
            .order_by(Decision.step).limit(settings.early_decisions)
        ).all()
    scored = Decision.episode_id == ep.id, Decision.nmse.is_not(None)
    before = s.execute(
        select(Decision.step, Decision.nmse).where(*scored, Decision.step <= ep.last_evaluated_step)
        .order_by(Decision.step.desc()).limit(settings.running_window)
    ).all()[::-1]
    after = s.execute(
        select(Decision.step, Decision.nmse).where(*scored, Decision.step > ep.last_evaluated_step).order_by(Decision.step)
    ).all()
    return [(r.step, r.nmse) for r in first], [(r.step, r.nmse) for r in before + after]


def rule_params(settings: MonitorSettings, kind: str | None = None) -> rules.RuleParams:
    """The alert rule the service runs now (its kind: the calibration's, or the settings' for a new one)."""
    return rules.RuleParams(kind or settings.alert_rule, settings.running_window, settings.alert_debounce,
                            settings.alert_clear_ratio)


def usable_rule(ctx: IngestContext, cal: CalibrationRow | None, task: str) -> tuple[rules.CalibratedRule | None, str]:
    """The calibrated rule to alert with, or None and the reason no alert can be raised (the episode's note)."""
    fix = f"`jepa-monitor calibrate --task {task}` (or POST /v1/calibrations)"
    if cal is None:
        return None, (f"no alerts: task {task!r} has no active calibration; record held-out labelled episodes "
                      f"and run {fix}")
    if "rule" not in cal.result:
        return None, (f"no alerts: calibration #{cal.id} predates episode-level alert rules (its threshold covered "
                      f"the early score only); recalibrate with {fix}")
    if cal.id not in ctx.calibrated_rules:
        ctx.calibrated_rules[cal.id] = rules.CalibratedRule.from_dict(cal.result["rule"])
    rule = ctx.calibrated_rules[cal.id]
    now = rule_params(ctx.settings, rule.params.kind)
    if rule.params != now:
        return None, (f"no alerts: calibration #{cal.id} holds for window={rule.params.window}, "
                      f"debounce={rule.params.debounce}, clear ratio={rule.params.clear_ratio}, but the service "
                      f"runs window={now.window}, debounce={now.debounce}, clear ratio={now.clear_ratio}; its "
                      f"false-alert guarantee does not cover that rule, so recalibrate with {fix}")
    return rule, (f"alerting when {rule.params.debounce} consecutive values of the {rule.params.kind} statistic "
                  f"(median of {rule.params.window}) exceed {rule.threshold:.6g}: calibration #{cal.id}, at most "
                  f"{rule.alpha:g} of successful episodes alert")


def refresh_episode(ctx: IngestContext, ep: Episode) -> None:
    """Update the early score, the running NMSE and the rule's statistic; step the alert state over the newly
    scored decisions.

    Every scored decision is considered once, in step order (``last_evaluated_step``); a decision scored after
    a later one was evaluated (out-of-order delivery) counts for the scores but is not evaluated for alerts.
    A task without a usable calibration consumes them without evaluation and the episode's ``alert_note`` says
    why (no calibration, or one made for other window / debounce / hysteresis settings).
    """
    s, settings = ctx.session, ctx.settings
    early = ep.early_score is None or ep.id in ctx.new_decision_episodes
    first, scored = _history(s, ep, settings, early)
    if early:   # the first decisions *by step*, whatever order they arrived in
        ep.early_score = scoring.early_score([v for _, v in first], settings.early_decisions)
    ep.n_scored += ctx.newly_scored.get(ep.id, 0)
    running = scoring.running_score([v for _, v in scored], settings.running_window)
    if running is not None:
        ep.running_score = running
    if (ep.task, ep.checkpoint) not in ctx.calibrations:
        ctx.calibrations[(ep.task, ep.checkpoint)] = active_calibration(s, ep.task, ep.checkpoint)
    cal = ctx.calibrations[(ep.task, ep.checkpoint)]
    rule, ep.alert_note = usable_rule(ctx, cal, ep.task)
    if rule is None:
        if scored:
            ep.last_evaluated_step = max(ep.last_evaluated_step, scored[-1][0])
        return
    steps = np.array([st for st, _ in scored], dtype=np.int64)
    values = rules.decision_values(rule.params, rules.EpisodeScores(steps, np.array([v for _, v in scored]), steps),
                                   rule.band)
    state = AlertState(ep.over_count, ep.under_count, ep.open_alert_id is not None)
    clear = rules.clear_level(rule.params, rule.threshold)
    window = rule.params.window
    for i, step in enumerate(steps.tolist()):
        if step <= ep.last_evaluated_step:
            continue
        ep.last_evaluated_step = step
        value = float(np.median(values[max(0, i + 1 - window): i + 1]))
        ep.risk_score = value
        state, event = step_alert(state, value, rule.threshold, rule.params.debounce, clear)
        if event == "raise":
            alert = Alert(
                episode_id=ep.id, task=ep.task, robot=ep.robot, step=step, score=value, threshold=rule.threshold,
                calibration_id=cal.id, state="open", note=f"{rule.params.kind} rule",
            )
            s.add(alert)
            s.flush()
            ep.open_alert_id = alert.id
            for url in settings.webhook_urls:
                s.add(WebhookDelivery(alert_id=alert.id, url=url, status="pending", attempts=0, last_error=""))
            ctx.alerts_raised.append(alert.id)
            ctx.observations.append(("alert", ep.task, ep.robot, 1.0))
        elif event == "clear":
            alert = s.get(Alert, ep.open_alert_id)
            alert.state, alert.cleared_at = "cleared", utcnow()
            ep.open_alert_id = None
    ep.over_count, ep.under_count = state.over, state.under


def ingest(ctx: IngestContext, records: list[DecisionIn | TargetIn | OutcomeIn]) -> None:
    """Apply records in order, then refresh every touched episode. Raises IngestError naming the bad record."""
    handlers = {"decision": _ingest_decision, "target": _ingest_target, "outcome": _ingest_outcome}
    with ctx.session.no_autoflush:
        ctx.preload(records)
        for i, rec in enumerate(records):
            try:
                handlers[rec.kind](ctx, rec)
            except IngestError as exc:
                if len(records) > 1:
                    raise IngestError(exc.status, f"records[{i}] ({rec.kind}): {exc.message}") from None
                raise
    ctx.session.flush()  # new episodes first: the decisions and targets refer to them
    ctx.write()
    for ep in ctx.dirty.values():
        refresh_episode(ctx, ep)


def publish_metrics(ctx: IngestContext) -> None:
    """Turn the committed request's observations into Prometheus samples."""
    counters = {"decision": metrics.DECISIONS, "target": metrics.TARGETS, "outcome": metrics.OUTCOMES, "alert": metrics.ALERTS}
    for kind, task, robot, value in ctx.observations:
        if kind == "nmse":
            metrics.NMSE.labels(task, robot).observe(value)
        else:
            counters[kind].labels(task, robot).inc(value)


def calibration_data(session: Session, task: str, checkpoint: str | None) -> list[calibration.LabelledEpisode]:
    """A task's held-out labelled episodes (optionally of one checkpoint) with every decision, in two queries."""
    q = select(Episode).where(Episode.task == task, Episode.held_out.is_(True), Episode.success.is_not(None))
    if checkpoint is not None:
        q = q.where(Episode.checkpoint == checkpoint)
    eps = {e.id: calibration.LabelledEpisode(e.id, bool(e.success), [], e.group, e.length)
           for e in session.scalars(q.order_by(Episode.id))}
    ids = list(eps)
    cols = Decision.episode_id, Decision.step, Decision.target_step, Decision.nmse, Decision.nmse_persistence
    for start in range(0, len(ids), 500):   # bounded IN lists
        for r in session.execute(select(*cols).where(Decision.episode_id.in_(ids[start:start + 500]))
                                 .order_by(Decision.episode_id, Decision.step)):
            eps[r.episode_id].decisions.append({"step": r.step, "target_step": r.target_step, "nmse": r.nmse,
                                                "nmse_persistence": r.nmse_persistence})
    return list(eps.values())


def calibrate_task(
    make_session, settings: MonitorSettings, task: str, checkpoint: str | None = None, alpha: float | None = None,
    rule: str | None = None, n_bootstrap: int | None = None, n_permutation: int | None = None,
    seed: int | None = None, folds: int | None = None,
) -> CalibrationRow:
    """Calibrate one task (optionally one checkpoint) from its held-out episodes and make it the active one.

    The alert rule is the service's (window, debounce, hysteresis) with ``rule`` or the settings' kind.
    Raises LookupError for an unknown task and ValueError when the data cannot support a calibration.
    """
    alpha = settings.alpha if alpha is None else alpha
    params = rule_params(settings, rule)
    with make_session() as session:
        if session.get(Task, task) is None:
            raise LookupError(f"task {task!r} is not registered; register it with PUT /v1/tasks/{task}")
        episodes = calibration_data(session, task, checkpoint)
        session.rollback()  # release the database while the resampling runs
    result = calibration.calibrate(
        episodes, params, alpha, folds=settings.detection_folds if folds is None else folds,
        early_decisions=settings.early_decisions,
        n_bootstrap=settings.n_bootstrap if n_bootstrap is None else n_bootstrap,
        n_permutation=settings.n_permutation if n_permutation is None else n_permutation,
        seed=settings.stats_seed if seed is None else seed,
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
