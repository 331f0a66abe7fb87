"""Applying one request's records, in order, to drafts of the episodes they touch: checks, pairing and scores.

A decision waits for the realized latent of its step t + k (or finds it stored); a target scores every decision
aimed at it. Nothing here writes: a bad record raises :class:`IngestError` before the request writes anything.
The NMSE of all of a request's new pairs is computed together at the end (:func:`compute_scores`).
"""
from __future__ import annotations

from bisect import insort
from typing import Protocol

import numpy as np

from monitor_service import scoring
from monitor_service.ingest import sql as statements
from monitor_service.ingest.sql import Sql
from monitor_service.ingest.state import Dec, EpisodeState, IngestError, Request, Tgt
from monitor_service.schemas import DecisionIn, OutcomeIn, TargetIn


class Episodes(Protocol):
    """What applying records needs of the store: drafts of episodes, the known latent sizes, the tasks'
    registered signals and the signals their active calibration covers."""

    sql: Sql
    task_dims: dict[str, int]

    def draft(self, cur, req: Request, episode_id: str) -> EpisodeState | None: ...

    def task_signals(self, cur, task: str) -> frozenset[str] | None: ...

    def calibrated_signals(self, cur, task: str, checkpoint: str | None) -> tuple[int, frozenset[str]] | None: ...


def apply_records(store: Episodes, cur, req: Request, records: list) -> None:
    """Apply ``records`` in order; a refusal names the record's index in a batch."""
    for i, rec in enumerate(records):
        try:
            HANDLERS[rec.kind](store, cur, req, rec)
        except IngestError as exc:
            if len(records) > 1:
                raise IngestError(exc.status, f"records[{i}] ({rec.kind}): {exc.message}") from None
            raise


def _check_dim(store: Episodes, cur, req: Request, task: str, dim: int, what: str) -> None:
    known = store.task_dims.get(task)
    if known == dim:   # the common case: the task's size, known to this process
        return
    known = known or req.task_dims.get(task)
    if known is None:
        found = statements.task_latent_dim(store.sql, cur, task, dim)
        if found is None:
            raise IngestError(404, f"task {task!r} is not registered; an admin registers it with PUT "
                                   f"/v1/tasks/{task} or `jepa-monitor tasks add {task}`")
        known, fixed_now = found
        if fixed_now:
            req.task_dims[task] = known
        else:
            store.task_dims[task] = known   # committed and never changes again
    if known != dim:
        raise IngestError(422, f"{what} has {dim} dimensions but task {task!r} uses latents of {known}; send "
                               "the encoder's full latent")


def _owned(req: Request, ep: EpisodeState) -> None:
    if ep.robot != req.principal.robot:
        raise IngestError(403, f"episode {ep.id!r} belongs to robot {ep.robot!r}; your key writes only for "
                               f"{req.principal.robot!r}")


def _known(store: Episodes, cur, req: Request, episode_id: str, what: str) -> EpisodeState:
    ep = store.draft(cur, req, episode_id)
    if ep is None:
        raise IngestError(404, f"episode {episode_id!r} is unknown; send its first decision before its {what}")
    _owned(req, ep)
    return ep


def _target_z(store: Episodes, cur, req: Request, ep: EpisodeState, step: int) -> bytes | None:
    t = ep.targets.get(step)
    if t is None:
        return None
    if t.z is not None:
        return t.z
    return statements.target_latent(store.sql, cur, req, ep.id, step)


def _stored_as(store: Episodes, cur, req: Request, ep: EpisodeState, step: int, d: Dec) -> tuple:
    """(horizon, z_hat, z_now, scores) of an existing decision: from memory while its latents are kept (or it
    sent none), else from its row."""
    if d.z_hat is not None or d.horizon is None or not d.stored:
        return d.horizon, d.z_hat, d.z_now, d.scores
    return statements.stored_decision(store.sql, cur, req, ep.id, step)


def _pair(req: Request, ep: EpisodeState, step: int, d: Dec, z: bytes) -> None:
    """Pair a decision with its realized latent; scored with the request's other pairs (``compute_scores``)."""
    ep.unscored.discard(step)
    req.to_score.append((ep, step, d, z))
    if d.stored:
        req.scored_stored.append((ep.id, step))
    req.scored += 1
    req.newly_scored[ep.id] = req.newly_scored.get(ep.id, 0) + 1


def _check_scores(store: Episodes, cur, rec: DecisionIn) -> None:
    """Every named score is a signal registered for the task, and a live episode's scores are covered by the
    task's active calibration (a score no calibration has seen could not be judged)."""
    registered = store.task_signals(cur, rec.task)
    if registered is None:
        raise IngestError(404, f"task {rec.task!r} is not registered; an admin registers it with PUT "
                               f"/v1/tasks/{rec.task} or `jepa-monitor tasks add {rec.task}`")
    unknown = sorted(set(rec.scores) - registered)
    if unknown:
        raise IngestError(422, f"task {rec.task!r} has no signal {unknown[0]!r} (its signals: "
                               f"{sorted(registered) or 'none'}); register it with PUT /v1/tasks/{rec.task} "
                               f"{{\"signals\": [\"{unknown[0]}\"]}} or `jepa-monitor tasks add {rec.task} --signals "
                               f"{unknown[0]}`")
    if rec.held_out:
        return
    covered = store.calibrated_signals(cur, rec.task, rec.checkpoint)
    if covered is not None and not set(rec.scores) <= covered[1]:
        missing = sorted(set(rec.scores) - covered[1])[0]
        raise IngestError(409, f"task {rec.task!r} is calibrated (calibration #{covered[0]}) without signal "
                               f"{missing!r}, so its live scores could not be judged; send {missing!r} on held-out "
                               "episodes (held_out: true) and recalibrate, or leave it out of live decisions")


def apply_decision(store: Episodes, cur, req: Request, rec: DecisionIn) -> None:
    if rec.z_hat is not None:
        _check_dim(store, cur, req, rec.task, rec.z_hat.shape[0], "z_hat")
    if rec.z_now is not None:
        _check_dim(store, cur, req, rec.task, rec.z_now.shape[0], "z_now")
    if rec.scores:
        _check_scores(store, cur, rec)
    robot = rec.robot or req.principal.robot
    if robot != req.principal.robot:
        raise IngestError(403, f"your key writes only for robot {req.principal.robot!r}, not {robot!r}")
    ep = store.draft(cur, req, rec.episode)
    if ep is None:
        ep = EpisodeState(rec.episode, rec.task, robot, rec.checkpoint, rec.group, rec.held_out, new=True)
        req.drafts[ep.id] = ep
    else:
        _owned(req, ep)
        if ep.task != rec.task or ep.robot != robot:
            raise IngestError(409, f"episode {ep.id!r} is task {ep.task!r} on robot {ep.robot!r}; episode ids "
                                   "must be unique")
        if ep.success is not None:
            raise IngestError(409, f"episode {ep.id!r} has ended (outcome recorded); start a new episode id")
    z_hat = None if rec.z_hat is None else rec.z_hat.tobytes()   # validated as little-endian float32 (schemas.Latent)
    z_now = None if rec.z_now is None else rec.z_now.tobytes()
    scores = rec.scores or None
    existing = ep.decisions.get(rec.step)
    if existing is not None:
        if _stored_as(store, cur, req, ep, rec.step, existing) == (rec.horizon, z_hat, z_now, scores):
            return   # the same record again: nothing to change, nothing double-counted
        raise IngestError(409, f"episode {ep.id!r} already has a different decision at step {rec.step}")
    d = Dec(rec.horizon, z_hat=z_hat, z_now=z_now, stored=False, scores=scores)
    ep.decisions[rec.step] = d
    for name, value in (rec.scores or {}).items():
        insort(ep.series.setdefault(name, []), (rec.step, float(value)))
        req.signal_observations.append(("score", ep.task, ep.robot, name, float(value)))
    skipped, late = ep.add_step(rec.step)
    if skipped:
        req.observations.append(("gap", ep.task, ep.robot, float(skipped)))
    if late:
        ep.late_decisions += 1
        req.observations.append(("late", ep.task, ep.robot, 1.0))
    req.new_decisions.append((ep.id, rec.step))
    if z_hat is not None:
        ep.unscored.add(rec.step)
        z = _target_z(store, cur, req, ep, rec.step + rec.horizon)
        if z is not None:
            _pair(req, ep, rec.step, d, z)
            ep.changed_target(rec.step + rec.horizon).z = None
    ep.n_decisions += 1
    req.counts["decision"] += 1
    req.observations.append(("decision", ep.task, ep.robot, 1.0))


def apply_target(store: Episodes, cur, req: Request, rec: TargetIn) -> None:
    ep = _known(store, cur, req, rec.episode, "targets")
    _check_dim(store, cur, req, ep.task, rec.z.shape[0], "z")
    z = rec.z.tobytes()
    existing = ep.targets.get(rec.step)
    if existing is not None:
        known = existing.z
        if known is None:   # used by a decision: its bytes are in this request or stored
            known = next((t for e, s, t in req.new_targets if e == ep.id and s == rec.step), None) or \
                statements.target_latent(store.sql, cur, req, ep.id, rec.step)
        if known == z:
            return
        raise IngestError(409, f"episode {ep.id!r} already has a different realized latent at step {rec.step}")
    aimed = sorted(step for step in ep.unscored if step + ep.decisions[step].horizon == rec.step)
    for step in aimed:
        d = ep.decisions[step]   # a decision of this request is the draft's own; a stored one is shared: copy it
        _pair(req, ep, step, ep.changed_decision(step) if d.stored else d, z)
    used = bool(aimed)
    ep.targets[rec.step] = Tgt(None if used else z)
    req.new_targets.append((ep.id, rec.step, z))
    req.counts["target"] += 1
    req.observations.append(("target", ep.task, ep.robot, 1.0))


def apply_outcome(store: Episodes, cur, req: Request, rec: OutcomeIn) -> None:
    ep = _known(store, cur, req, rec.episode, "outcome")
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
    ep.ended = True
    req.ended.add(ep.id)
    req.counts["outcome"] += 1
    req.observations.append(("outcome", ep.task, ep.robot, 1.0))


HANDLERS = {"decision": apply_decision, "target": apply_target, "outcome": apply_outcome}


def compute_scores(req: Request) -> None:
    """NMSE (and the persistence baseline's, Sec. 4.10, and their ratio, the ``nmse_ratio`` signal) of the
    request's new pairs, one array operation per latent size instead of one call per decision."""
    by_dim: dict[int, list] = {}
    for item in req.to_score:
        by_dim.setdefault(len(item[3]) // 4, []).append(item)
    for dim, items in by_dim.items():
        def rows(latents):
            return np.frombuffer(b"".join(latents), dtype="<f4").reshape(len(latents), dim)
        targets = rows([z for _, _, _, z in items])
        values = scoring.nmse_rows(rows([d.z_hat for _, _, d, _ in items]), targets).tolist()
        with_now = [i for i, (_, _, d, _) in enumerate(items) if d.z_now is not None]
        persistence = scoring.nmse_rows(rows([items[i][2].z_now for i in with_now]), targets[with_now]).tolist() \
            if with_now else []
        ratios = scoring.nmse_ratio([values[i] for i in with_now], persistence).tolist() if with_now else []
        for i, value, ratio in zip(with_now, persistence, ratios):
            ep, step, d, _ = items[i]
            d.nmse_persistence = value
            if ratio == ratio:   # the service's second signal; none for a frozen scene (scoring.nmse_ratio)
                insort(ep.series.setdefault(scoring.RATIO, []), (step, ratio))
                req.signal_observations.append(("score", ep.task, ep.robot, scoring.RATIO, ratio))
        for (ep, step, d, _), value in zip(items, values):
            d.nmse = value
            if d.stored:   # a new decision keeps its latents until they are written
                d.z_hat = d.z_now = None
            scored = ep.scored
            if not scored or scored[-1][0] < step:   # in step order, as most pairs come: no search
                scored.append((step, value))
            else:
                insort(scored, (step, value))
            req.observations.append(("nmse", ep.task, ep.robot, value))
