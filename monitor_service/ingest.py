"""The ingest path: decisions, realized latents and outcomes applied in one transaction, fast enough for a fleet.

Per request the records are applied in order to *drafts* of the touched episodes' state, checked and scored in
memory; then the rows are written with a few bulk statements on the raw database connection, the alert rule is
stepped over the newly scored decisions, and everything commits together. A bad record raises
:class:`IngestError` before anything is written, so nothing already accepted is lost or changed.

Episode state (counters, scores, alert state, which decisions and targets exist, the latents still waiting for
their partner) is kept in memory between requests and is the database's, not a second truth. Each request first
locks the rows of the episodes it touches (PostgreSQL: SELECT ... FOR UPDATE; SQLite: the write transaction)
and reads their version counters: a cached state whose version differs was changed by another process (a second
worker, a second server on PostgreSQL) and is reloaded. Every write bumps the version. Two requests creating the
same new episode at once conflict on its primary key; the loser is retried once. The active calibration is
cached for a second and cleared at once when this process calibrates.
"""
from __future__ import annotations

import copy
import hashlib
import json
import statistics
import time
from bisect import bisect_right, insort
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np

from monitor_service import rules, scoring
from monitor_service.alerts import AlertState, step_alert
from monitor_service.auth import Principal
from monitor_service.db import utcnow
from monitor_service.schemas import DecisionIn, OutcomeIn, TargetIn
from monitor_service.settings import MonitorSettings

CACHE_EPISODES = 20_000      # live episodes kept in memory (least recently used leave first)
CALIBRATION_TTL_S = 1.0      # another process's new calibration is seen within this time


class IngestError(Exception):
    """A record the service refuses; ``status`` is the HTTP status, the message names problem and fix."""

    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status = status
        self.message = message


class StaleState(Exception):
    """Another process changed an episode this request read; retry on fresh state."""


# What recognises an identical resend: SHA-256 (the CPU's SHA instructions make it about twice as quick as
# BLAKE2b on a 4 KB latent here). Latents of one task have one fixed size, so the parts cannot shift.
def decision_digest(horizon: int, z_hat: bytes, z_now: bytes | None) -> bytes:
    h = hashlib.sha256(z_hat)
    h.update(b"|%d|" % horizon)
    if z_now is not None:
        h.update(z_now)
    return h.digest()


def target_digest(z: bytes) -> bytes:
    return hashlib.sha256(z).digest()


@dataclass(slots=True)
class Dec:
    """A decision of an episode: what is needed to score it, recognise a resend, and step the alert rule."""

    horizon: int
    digest: bytes                     # of (horizon, z_hat, z_now): an identical resend changes nothing
    nmse: float | None = None
    nmse_persistence: float | None = None
    z_hat: bytes | None = None        # kept only while unscored
    z_now: bytes | None = None
    stored: bool = True               # False: inserted by the current request

    def copy(self) -> "Dec":   # ~4x quicker than copy.copy on the ingest path
        return Dec(self.horizon, self.digest, self.nmse, self.nmse_persistence, self.z_hat, self.z_now, self.stored)


@dataclass(slots=True)
class Tgt:
    digest: bytes
    z: bytes | None = None            # kept only while no decision has used it

    def copy(self) -> "Tgt":
        return Tgt(self.digest, self.z)


@dataclass
class EpisodeState:
    """One episode's row plus its decisions and targets (latents only where still needed)."""

    id: str
    task: str
    robot: str
    checkpoint: str | None
    group: str | None
    held_out: bool
    success: bool | None = None
    length: int | None = None
    version: int = 0
    n_decisions: int = 0
    n_scored: int = 0
    last_evaluated_step: int = -1
    over_count: int = 0
    under_count: int = 0
    open_alert_id: int | None = None
    early_score: float | None = None
    running_score: float | None = None
    risk_score: float | None = None
    alert_note: str = ""
    ended: bool = False               # an outcome arrived (ended_at set)
    new: bool = False                 # created by the current request
    decisions: dict[int, Dec] = field(default_factory=dict)
    targets: dict[int, Tgt] = field(default_factory=dict)
    scored: list[tuple[int, float]] = field(default_factory=list)   # (step, nmse), sorted by step
    unscored: set[int] = field(default_factory=set)                   # steps of decisions without a target yet

    def draft(self) -> "EpisodeState":
        """A copy the current request may change; the cache keeps the original until commit. The decisions
        and targets are shared until one is changed (``changed_decision``, ``changed_target``)."""
        d = copy.copy(self)
        d.decisions = dict(self.decisions)
        d.targets = dict(self.targets)
        d.scored = list(self.scored)
        d.unscored = set(self.unscored)
        return d

    def changed_decision(self, step: int) -> Dec:
        dec = self.decisions[step] = self.decisions[step].copy()
        return dec

    def changed_target(self, step: int) -> Tgt:
        tgt = self.targets[step] = self.targets[step].copy()
        return tgt


EPISODE_COLUMNS = ("id, task, robot, checkpoint, group_name, held_out, success, length, version, n_decisions, "
                   "n_scored, last_evaluated_step, over_count, under_count, open_alert_id, early_score, "
                   "running_score, risk_score, alert_note, ended_at")


class Sql:
    """Statements in the database's own parameter style (sqlite3: ?, psycopg2: %s), on a raw DB-API cursor."""

    def __init__(self, dialect: str):
        self.dialect = dialect
        self.mark = "?" if dialect == "sqlite" else "%s"

    def q(self, text: str) -> str:
        return text if self.mark == "?" else text.replace("?", "%s")

    def begin(self, cur) -> None:
        if self.dialect == "sqlite":
            cur.execute("BEGIN IMMEDIATE")   # a writer from the start: never an upgrade from reader (locks)

    def commit(self, conn, cur) -> None:
        if self.dialect == "sqlite":
            cur.execute("COMMIT")
        else:
            conn.commit()

    def rollback(self, conn, cur) -> None:
        if self.dialect != "sqlite":
            conn.rollback()
        elif conn.in_transaction:
            cur.execute("ROLLBACK")

    def insert_many(self, cur, table: str, columns: str, rows: list[tuple]) -> None:
        """One statement for all rows: sqlite3's executemany runs it in C; psycopg2's executemany would send one
        statement per row, so PostgreSQL gets a single multi-row INSERT (execute_values)."""
        if self.dialect == "sqlite":
            marks = ", ".join("?" * (columns.count(",") + 1))
            cur.executemany(f"INSERT INTO {table} ({columns}) VALUES ({marks})", rows)
        else:
            from psycopg2.extras import execute_values
            execute_values(cur, f"INSERT INTO {table} ({columns}) VALUES %s", rows, page_size=len(rows))

    def set_scores(self, cur, rows: list[tuple]) -> None:
        """``UPDATE decisions SET nmse, nmse_persistence`` for (nmse, persistence, episode_id, step) rows."""
        if self.dialect == "sqlite":
            cur.executemany("UPDATE decisions SET nmse = ?, nmse_persistence = ? WHERE episode_id = ? AND step = ?",
                            rows)
        else:
            from psycopg2.extras import execute_values
            execute_values(cur, "UPDATE decisions AS d SET nmse = v.nmse, nmse_persistence = v.pers FROM (VALUES %s) "
                                "AS v (nmse, pers, episode_id, step) WHERE d.episode_id = v.episode_id AND "
                                "d.step = v.step", rows, template="(%s::float8, %s::float8, %s, %s)",
                           page_size=len(rows))

    def time(self, value):
        """A naive-UTC datetime as this database stores it (SQLite: SQLAlchemy's text format)."""
        return value.strftime("%Y-%m-%d %H:%M:%S.%f") if self.dialect == "sqlite" else value


@dataclass
class Request:
    """What one ingest request changes and reports, built in memory, written at the end."""

    principal: Principal
    drafts: dict[str, EpisodeState] = field(default_factory=dict)
    new_targets: list[tuple] = field(default_factory=list)
    new_decisions: list[tuple[str, int]] = field(default_factory=list)  # (episode, step) created now
    scored_stored: list[tuple[str, int]] = field(default_factory=list)  # stored decisions scored now
    newly_scored: dict[str, int] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=lambda: {"decision": 0, "target": 0, "outcome": 0})
    observations: list[tuple[str, str, str, float]] = field(default_factory=list)
    alerts_raised: list[int] = field(default_factory=list)
    scored: int = 0
    task_dims: dict[str, int] = field(default_factory=dict)           # latent_dim fixed by this request
    to_score: list[tuple[EpisodeState, int, Dec, bytes]] = field(default_factory=list)   # (ep, step, dec, z)


class IngestStore:
    """Applies ingest requests for one app (one process); see the module docstring."""

    def __init__(self, engine, settings: MonitorSettings):
        self.engine = engine
        self.settings = settings
        self.sql = Sql(engine.dialect.name)
        # SQLite commits in well under a millisecond on this host (WAL, no fsync per commit): a request is applied on
        # the event loop, which saves the thread hand-over that cost more than the work. PostgreSQL statements
        # wait on the network and on row locks, so they run in the thread pool.
        self.inline = engine.dialect.name == "sqlite"
        self.episodes: OrderedDict[str, EpisodeState] = OrderedDict()
        self.task_dims: dict[str, int] = {}
        self.calibrations: dict[tuple[str, str | None], tuple[float, object]] = {}
        self.rules: dict[int, rules.CalibratedRule] = {}

    # ------------------------------------------------------------------ caches
    def forget_calibrations(self) -> None:
        self.calibrations.clear()

    def _remember(self, ep: EpisodeState) -> None:
        self.episodes[ep.id] = ep
        self.episodes.move_to_end(ep.id)
        while len(self.episodes) > CACHE_EPISODES:
            self.episodes.popitem(last=False)

    # ------------------------------------------------------------------ entry point
    def apply(self, records: list, principal: Principal, idem: tuple[int, str, str] | None = None) -> tuple[dict, Request]:
        """Apply ``records`` in one transaction and return (result, the committed request's record).

        ``idem`` = (api key id, Idempotency-Key, body hash): stored with the result in the same transaction.
        Raises IngestError (nothing written), or StaleState when another process wrote a touched episode (or
        the same Idempotency-Key) meanwhile: nothing written, the touched episodes reload next time.
        """
        conn = self.engine.raw_connection()
        try:
            cur = conn.cursor()
            try:
                self.sql.begin(cur)
                self._lock_and_validate(cur, records)
                req = Request(principal)
                self._apply_records(cur, req, records)
                self._write(cur, req)
                result = {"accepted": len(records), "decisions": req.counts["decision"],
                          "targets": req.counts["target"], "outcomes": req.counts["outcome"],
                          "scored": req.scored, "alerts_raised": req.alerts_raised,
                          "alert_state": {ep.id: ep.open_alert_id for ep in req.drafts.values()}}
                if idem is not None:
                    self._store_idempotency(cur, idem, result)
                self.sql.commit(conn, cur)
            except BaseException as exc:
                self.sql.rollback(conn, cur)
                if isinstance(exc, (StaleState, self.engine.dialect.dbapi.IntegrityError)):
                    for eid in {getattr(r, "episode", None) for r in records}:
                        self.episodes.pop(eid, None)
                    raise StaleState("a concurrent request wrote the same episode or key") from None
                raise
            finally:
                cur.close()
        finally:
            conn.close()
        for eid, step in req.new_decisions:   # created by this request: its own objects, not shared
            d = req.drafts[eid].decisions[step]
            d.stored = True
            if d.nmse is not None:
                d.z_hat = d.z_now = None
        for ep in req.drafts.values():
            ep.new = False
            self._remember(ep)
        self.task_dims.update(req.task_dims)
        return result, req

    # ------------------------------------------------------------------ state
    def _lock_and_validate(self, cur, records: list) -> None:
        """Lock the touched episodes' rows (PostgreSQL: FOR UPDATE, in id order; SQLite: the transaction is a
        writer already) and drop cached states that another process has changed since."""
        ids = sorted({r.episode for r in records})
        marks = ", ".join([self.sql.mark] * len(ids))
        lock = "" if self.sql.dialect == "sqlite" else " FOR UPDATE"
        cur.execute(f"SELECT id, version FROM episodes WHERE id IN ({marks}) ORDER BY id{lock}", ids)
        for episode_id, version in cur.fetchall():
            cached = self.episodes.get(episode_id)
            if cached is not None and cached.version != version:
                del self.episodes[episode_id]

    def _episode(self, cur, req: Request, episode_id: str) -> EpisodeState | None:
        """The request's draft of an episode (loaded from the database on a cache miss), or None if unknown."""
        if episode_id in req.drafts:
            return req.drafts[episode_id]
        ep = self.episodes.get(episode_id)
        if ep is None:
            ep = self._load(cur, episode_id)
            if ep is None:
                return None
            self._remember(ep)
        draft = ep.draft()
        req.drafts[episode_id] = draft
        return draft

    def _load(self, cur, episode_id: str) -> EpisodeState | None:
        q = self.sql.q
        cur.execute(q(f"SELECT {EPISODE_COLUMNS} FROM episodes WHERE id = ?"), (episode_id,))
        row = cur.fetchone()
        if row is None:
            return None
        ep = EpisodeState(row[0], row[1], row[2], row[3], row[4], bool(row[5]),
                          None if row[6] is None else bool(row[6]), row[7], row[8], row[9], row[10], row[11],
                          row[12], row[13], row[14], row[15], row[16], row[17], row[18], ended=row[19] is not None)
        cur.execute(q("SELECT step, horizon, nmse, nmse_persistence, z_hat, z_now FROM decisions "
                      "WHERE episode_id = ? ORDER BY step"), (episode_id,))
        for step, horizon, nmse, pers, z_hat, z_now in cur.fetchall():
            z_hat, z_now = bytes(z_hat), None if z_now is None else bytes(z_now)
            d = Dec(horizon, decision_digest(horizon, z_hat, z_now), nmse, pers)
            if nmse is None:
                d.z_hat, d.z_now = z_hat, z_now
                ep.unscored.add(step)
            else:
                ep.scored.append((step, nmse))
            ep.decisions[step] = d
        aimed = {s + d.horizon for s, d in ep.decisions.items()}
        cur.execute(q("SELECT step, z FROM targets WHERE episode_id = ?"), (episode_id,))
        for step, z in cur.fetchall():
            z = bytes(z)
            ep.targets[step] = Tgt(target_digest(z), None if step in aimed else z)
        return ep

    def _target_z(self, cur, ep: EpisodeState, step: int) -> bytes | None:
        t = ep.targets.get(step)
        if t is None:
            return None
        if t.z is not None:
            return t.z
        cur.execute(self.sql.q("SELECT z FROM targets WHERE episode_id = ? AND step = ?"), (ep.id, step))
        row = cur.fetchone()
        return None if row is None else bytes(row[0])

    # ------------------------------------------------------------------ records
    def _apply_records(self, cur, req: Request, records: list) -> None:
        handlers = {"decision": self._decision, "target": self._target, "outcome": self._outcome}
        for i, rec in enumerate(records):
            try:
                handlers[rec.kind](cur, req, rec)
            except IngestError as exc:
                if len(records) > 1:
                    raise IngestError(exc.status, f"records[{i}] ({rec.kind}): {exc.message}") from None
                raise

    def _check_dim(self, cur, req: Request, task: str, dim: int, what: str) -> None:
        known = self.task_dims.get(task) or req.task_dims.get(task)
        if known is None:
            cur.execute(self.sql.q("SELECT latent_dim FROM tasks WHERE name = ?"), (task,))
            row = cur.fetchone()
            if row is None:
                raise IngestError(404, f"task {task!r} is not registered; an admin registers it with PUT "
                                       f"/v1/tasks/{task} or `jepa-monitor tasks add {task}`")
            known = row[0]
            if known is None:   # the first latent fixes the size; a concurrent first latent cannot fix another
                cur.execute(self.sql.q("UPDATE tasks SET latent_dim = ? WHERE name = ? AND latent_dim IS NULL"),
                            (dim, task))
                cur.execute(self.sql.q("SELECT latent_dim FROM tasks WHERE name = ?"), (task,))
                known = cur.fetchone()[0]
                req.task_dims[task] = known
            else:
                self.task_dims[task] = known   # committed and never changes again
        if known != dim:
            raise IngestError(422, f"{what} has {dim} dimensions but task {task!r} uses latents of {known}; send "
                                   "the encoder's full latent")

    def _owned(self, req: Request, ep: EpisodeState) -> None:
        if ep.robot != req.principal.robot:
            raise IngestError(403, f"episode {ep.id!r} belongs to robot {ep.robot!r}; your key writes only for "
                                   f"{req.principal.robot!r}")

    def _score(self, req: Request, ep: EpisodeState, step: int, d: Dec, z: bytes) -> None:
        """Pair a decision with its realized latent; the NMSE of all of a request's pairs is computed together
        (``_compute_scores``) before anything reads it."""
        ep.unscored.discard(step)
        req.to_score.append((ep, step, d, z))
        if d.stored:
            req.scored_stored.append((ep.id, step))
        req.scored += 1
        req.newly_scored[ep.id] = req.newly_scored.get(ep.id, 0) + 1

    def _compute_scores(self, req: Request) -> None:
        """NMSE (and the persistence baseline's, Sec. 4.10) of the request's new pairs, one array operation per
        latent size instead of one call per decision."""
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
            for i, value in zip(with_now, persistence):
                items[i][2].nmse_persistence = value
            for (ep, step, d, _), value in zip(items, values):
                d.nmse = value
                if d.stored:   # a new decision keeps its latents until they are written
                    d.z_hat = d.z_now = None
                insort(ep.scored, (step, value))
                req.observations.append(("nmse", ep.task, ep.robot, value))

    def _decision(self, cur, req: Request, rec: DecisionIn) -> None:
        self._check_dim(cur, req, rec.task, rec.z_hat.shape[0], "z_hat")
        if rec.z_now is not None:
            self._check_dim(cur, req, rec.task, rec.z_now.shape[0], "z_now")
        robot = rec.robot or req.principal.robot
        if robot != req.principal.robot:
            raise IngestError(403, f"your key writes only for robot {req.principal.robot!r}, not {robot!r}")
        ep = self._episode(cur, req, rec.episode)
        if ep is None:
            ep = EpisodeState(rec.episode, rec.task, robot, rec.checkpoint, rec.group, rec.held_out, new=True)
            req.drafts[ep.id] = ep
        else:
            self._owned(req, ep)
            if ep.task != rec.task or ep.robot != robot:
                raise IngestError(409, f"episode {ep.id!r} is task {ep.task!r} on robot {ep.robot!r}; episode ids "
                                       "must be unique")
            if ep.success is not None:
                raise IngestError(409, f"episode {ep.id!r} has ended (outcome recorded); start a new episode id")
        z_hat = rec.z_hat.tobytes()   # validated as little-endian float32 (schemas.Latent)
        z_now = None if rec.z_now is None else rec.z_now.tobytes()
        digest = decision_digest(rec.horizon, z_hat, z_now)
        existing = ep.decisions.get(rec.step)
        if existing is not None:
            if existing.digest == digest:
                return   # the same record again: nothing to change, nothing double-counted
            raise IngestError(409, f"episode {ep.id!r} already has a different decision at step {rec.step}")
        d = Dec(rec.horizon, digest, z_hat=z_hat, z_now=z_now, stored=False)
        ep.decisions[rec.step] = d
        ep.unscored.add(rec.step)
        req.new_decisions.append((ep.id, rec.step))
        z = self._target_z(cur, ep, rec.step + rec.horizon)
        if z is not None:
            self._score(req, ep, rec.step, d, z)
            ep.changed_target(rec.step + rec.horizon).z = None
        ep.n_decisions += 1
        req.counts["decision"] += 1
        req.observations.append(("decision", ep.task, ep.robot, 1.0))

    def _known(self, cur, req: Request, episode_id: str, what: str) -> EpisodeState:
        ep = self._episode(cur, req, episode_id)
        if ep is None:
            raise IngestError(404, f"episode {episode_id!r} is unknown; send its first decision before its {what}")
        self._owned(req, ep)
        return ep

    def _target(self, cur, req: Request, rec: TargetIn) -> None:
        ep = self._known(cur, req, rec.episode, "targets")
        self._check_dim(cur, req, ep.task, rec.z.shape[0], "z")
        z = rec.z.tobytes()
        digest = target_digest(z)
        existing = ep.targets.get(rec.step)
        if existing is not None:
            if existing.digest == digest:
                return
            raise IngestError(409, f"episode {ep.id!r} already has a different realized latent at step {rec.step}")
        aimed = sorted(step for step in ep.unscored if step + ep.decisions[step].horizon == rec.step)
        for step in aimed:
            self._score(req, ep, step, ep.changed_decision(step), z)
        used = bool(aimed)
        ep.targets[rec.step] = Tgt(digest, None if used else z)
        req.new_targets.append((ep.id, rec.step, z))
        req.counts["target"] += 1
        req.observations.append(("target", ep.task, ep.robot, 1.0))

    def _outcome(self, cur, req: Request, rec: OutcomeIn) -> None:
        ep = self._known(cur, req, rec.episode, "outcome")
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
        req.counts["outcome"] += 1
        req.observations.append(("outcome", ep.task, ep.robot, 1.0))

    # ------------------------------------------------------------------ scores and alerts
    def _calibrated_rule(self, cur, task: str, checkpoint: str | None) -> tuple[int | None, dict | None]:
        """(id, result) of the active calibration of a checkpoint, else of its task; cached briefly."""
        key = (task, checkpoint)
        hit = self.calibrations.get(key)
        now = time.monotonic()
        if hit is not None and now - hit[0] < CALIBRATION_TTL_S:
            return hit[1]
        found = (None, None)
        for ckpt in ([checkpoint] if checkpoint is not None else []) + [None]:
            cond = "checkpoint IS NULL" if ckpt is None else "checkpoint = ?"
            cur.execute(self.sql.q(f"SELECT id, result FROM calibrations WHERE task = ? AND {cond} AND active = ?"
                                   " ORDER BY id DESC"), (task, True) if ckpt is None else (task, ckpt, True))
            row = cur.fetchone()
            if row is not None:   # JSON column: text on SQLite, already decoded by psycopg2
                found = (row[0], row[1] if isinstance(row[1], dict) else json.loads(row[1]))
                break
        self.calibrations[key] = (now, found)
        return found

    def _usable_rule(self, cur, ep: EpisodeState) -> tuple[int | None, rules.CalibratedRule | None, str]:
        cal_id, result = self._calibrated_rule(cur, ep.task, ep.checkpoint)
        fix = f"`jepa-monitor calibrate --task {ep.task}` (or POST /v1/calibrations)"
        if cal_id is None:
            return None, None, (f"no alerts: task {ep.task!r} has no active calibration; record held-out labelled "
                                f"episodes and run {fix}")
        if "rule" not in result:
            return cal_id, None, (f"no alerts: calibration #{cal_id} predates episode-level alert rules (its "
                                  f"threshold covered the early score only); recalibrate with {fix}")
        if cal_id not in self.rules:
            self.rules[cal_id] = rules.CalibratedRule.from_dict(result["rule"])
        rule = self.rules[cal_id]
        now = rule_params(self.settings, rule.params.kind)
        if rule.params != now:
            return cal_id, None, (
                f"no alerts: calibration #{cal_id} holds for window={rule.params.window}, "
                f"debounce={rule.params.debounce}, clear ratio={rule.params.clear_ratio}, but the service runs "
                f"window={now.window}, debounce={now.debounce}, clear ratio={now.clear_ratio}; its false-alert "
                f"guarantee does not cover that rule, so recalibrate with {fix}")
        return cal_id, rule, (
            f"alerting when {rule.params.debounce} consecutive values of the {rule.params.kind} statistic (median "
            f"of {rule.params.window}) exceed {rule.threshold:.6g}: calibration #{cal_id}, at most {rule.alpha:g} "
            f"of successful episodes alert")

    def _refresh(self, cur, req: Request, ep: EpisodeState) -> None:
        """Early score (the first decisions by step), running NMSE, and the alert rule over the decisions scored
        since the last evaluated step, in step order. A decision scored after a later one was evaluated counts
        for the scores but is not evaluated for alerts."""
        settings = self.settings
        first = [ep.decisions[s].nmse for s in sorted(ep.decisions)[: settings.early_decisions]]
        ep.early_score = scoring.early_score(first, settings.early_decisions)
        ep.n_scored += req.newly_scored.get(ep.id, 0)
        running = scoring.running_score([v for _, v in ep.scored], settings.running_window)
        if running is not None:
            ep.running_score = running
        first_new = bisect_right(ep.scored, (ep.last_evaluated_step, float("inf")))
        todo = range(first_new, len(ep.scored))
        if not todo:
            return
        cal_id, rule, ep.alert_note = self._usable_rule(cur, ep)
        if rule is None:
            ep.last_evaluated_step = ep.scored[-1][0]
            return
        window = rule.params.window
        lo = max(0, todo[0] + 1 - window)
        part = ep.scored[lo:]
        steps = np.array([s for s, _ in part], dtype=np.int64)
        values = rules.decision_values(rule.params, rules.EpisodeScores(steps, np.array([v for _, v in part]), steps),
                                       rule.band).tolist()
        state = AlertState(ep.over_count, ep.under_count, ep.open_alert_id is not None)
        clear = rules.clear_level(rule.params, rule.threshold)
        for i in todo:
            j = i - lo
            step = int(steps[j])
            ep.last_evaluated_step = step
            value = float(statistics.median(values[max(0, j + 1 - window): j + 1]))
            ep.risk_score = value
            state, event = step_alert(state, value, rule.threshold, rule.params.debounce, clear)
            if event == "raise":
                ep.open_alert_id = self._raise(cur, req, ep, cal_id, step, value, rule.threshold, rule.params.kind)
            elif event == "clear":
                cur.execute(self.sql.q("UPDATE alerts SET state = ?, cleared_at = ? WHERE id = ?"),
                            ("cleared", self.sql.time(utcnow()), ep.open_alert_id))
                ep.open_alert_id = None
        ep.over_count, ep.under_count = state.over, state.under

    def _raise(self, cur, req: Request, ep: EpisodeState, cal_id: int, step: int, value: float, threshold: float,
               kind: str) -> int:
        cur.execute(self.sql.q(
            "INSERT INTO alerts (episode_id, task, robot, step, score, threshold, calibration_id, state, note, "
            "raised_at) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?) RETURNING id"),
            (ep.id, ep.task, ep.robot, step, value, threshold, cal_id, "open", f"{kind} rule", self.sql.time(utcnow())))
        alert_id = cur.fetchone()[0]
        if self.settings.webhook_urls:
            now = self.sql.time(utcnow())
            cur.executemany(self.sql.q(
                "INSERT INTO webhook_deliveries (alert_id, url, status, attempts, next_attempt_at, last_error) "
                "VALUES (?, ?, ?, ?, ?, ?)"), [(alert_id, url, "pending", 0, now, "") for url in self.settings.webhook_urls])
        req.alerts_raised.append(alert_id)
        req.observations.append(("alert", ep.task, ep.robot, 1.0))
        return alert_id

    # ------------------------------------------------------------------ writing
    def _write(self, cur, req: Request) -> None:
        self._compute_scores(req)
        q, now = self.sql.q, self.sql.time(utcnow())
        for ep in req.drafts.values():
            if ep.new:
                cur.execute(q(
                    "INSERT INTO episodes (id, task, robot, checkpoint, group_name, held_out, n_decisions, n_scored, "
                    "last_evaluated_step, over_count, under_count, alert_note, started_at, updated_at, version) "
                    "VALUES (?, ?, ?, ?, ?, ?, 0, 0, -1, 0, 0, '', ?, ?, 0)"),
                    (ep.id, ep.task, ep.robot, ep.checkpoint, ep.group, ep.held_out, now, now))
        rows = [(eid, step, d.horizon, step + d.horizon, d.z_hat, d.nmse, d.z_now, d.nmse_persistence, now)
                for eid, step in req.new_decisions for d in [req.drafts[eid].decisions[step]]]
        if rows:
            self.sql.insert_many(cur, "decisions", "episode_id, step, horizon, target_step, z_hat, nmse, z_now, "
                                                   "nmse_persistence, created_at", rows)
        if req.new_targets:
            self.sql.insert_many(cur, "targets", "episode_id, step, z, created_at",
                                 [(eid, step, z, now) for eid, step, z in req.new_targets])
        if req.scored_stored:
            self.sql.set_scores(cur, [(req.drafts[eid].decisions[s].nmse, req.drafts[eid].decisions[s].nmse_persistence,
                                       eid, s) for eid, s in req.scored_stored])
        for ep in req.drafts.values():
            self._refresh(cur, req, ep)
            cur.execute(q(
                "UPDATE episodes SET version = ?, group_name = ?, held_out = ?, success = ?, length = ?, "
                "n_decisions = ?, n_scored = ?, last_evaluated_step = ?, over_count = ?, under_count = ?, "
                "open_alert_id = ?, early_score = ?, running_score = ?, risk_score = ?, alert_note = ?, "
                "updated_at = ?, ended_at = COALESCE(ended_at, ?) WHERE id = ? AND version = ?"),
                (ep.version + 1, ep.group, ep.held_out, ep.success, ep.length, ep.n_decisions, ep.n_scored,
                 ep.last_evaluated_step, ep.over_count, ep.under_count, ep.open_alert_id, ep.early_score,
                 ep.running_score, ep.risk_score, ep.alert_note[:512], now, now if ep.ended else None, ep.id,
                 ep.version))
            if cur.rowcount != 1:
                raise StaleState(f"episode {ep.id!r} changed in another process")
            ep.version += 1

    def idempotent_answer(self, key_id: int, key: str) -> tuple[str, int, dict] | None:
        """(body hash, status, answer) stored for this key's Idempotency-Key, or None."""
        conn = self.engine.raw_connection()
        try:
            cur = conn.cursor()
            cur.execute(self.sql.q("SELECT request_hash, status_code, response FROM idempotency_keys "
                                   "WHERE api_key_id = ? AND key = ?"), (key_id, key))
            row = cur.fetchone()
            cur.close()
            if self.sql.dialect != "sqlite":
                conn.rollback()
        finally:
            conn.close()
        if row is None:
            return None
        return row[0], row[1], row[2] if isinstance(row[2], dict) else json.loads(row[2])

    def _store_idempotency(self, cur, idem: tuple[int, str, str], result: dict) -> None:
        key_id, key, body_hash = idem
        cur.execute(self.sql.q("INSERT INTO idempotency_keys (api_key_id, key, request_hash, status_code, response, "
                               "created_at) VALUES (?, ?, ?, ?, ?, ?)"),
                    (key_id, key, body_hash, 200, json.dumps(result), self.sql.time(utcnow())))


def rule_params(settings: MonitorSettings, kind: str | None = None) -> rules.RuleParams:
    """The alert rule the service runs now (its kind: the calibration's, or the settings' for a new one)."""
    return rules.RuleParams(kind or settings.alert_rule, settings.running_window, settings.alert_debounce,
                            settings.alert_clear_ratio)
