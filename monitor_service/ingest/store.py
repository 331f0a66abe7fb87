"""The ingest transaction: lock the touched episodes, apply the records to drafts, write, evaluate, commit.

Episode state is kept in memory between requests (``state.py``) and is the database's, not a second truth: each
request first locks the rows of the episodes it touches (PostgreSQL: SELECT ... FOR UPDATE; SQLite: the write
transaction) and reads their version counters; a cached state whose version differs was changed by another
process (a second worker, a second server on PostgreSQL) and is reloaded. Every write bumps the version. Two
requests creating the same new episode at once conflict on its primary key; the loser is retried once (by the
router). A bad record raises :class:`IngestError` before anything is written, so nothing already accepted is
lost or changed.
"""
from __future__ import annotations

import time
from collections import OrderedDict

from monitor_service.auth import Principal
from monitor_service.db import utcnow
from monitor_service.ingest import sql as statements
from monitor_service.ingest.alerting import Alerting
from monitor_service.ingest.records import apply_records, compute_scores
from monitor_service.ingest.sql import Sql
from monitor_service.ingest.state import EpisodeState, Request, StaleState
from monitor_service.settings import MonitorSettings

CACHE_EPISODES = 20_000      # live episodes kept in memory (least recently used leave first)
TASK_TTL_S = 1.0             # another process's newly registered signal is accepted within this time


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
        self.signals: dict[str, tuple[float, frozenset[str] | None]] = {}
        self.alerting = Alerting(self.sql, settings)

    def forget_calibrations(self) -> None:
        """Alert with a new calibration from the next record on (this process calibrated)."""
        self.alerting.forget_calibrations()

    def forget_tasks(self) -> None:
        """Accept a task's newly registered signals from the next record on (this process registered them)."""
        self.signals.clear()

    def task_signals(self, cur, task: str) -> frozenset[str] | None:
        """The task's registered signals (None: no such task), cached briefly."""
        hit = self.signals.get(task)
        now = time.monotonic()
        if hit is not None and now - hit[0] < TASK_TTL_S:
            return hit[1]
        found = statements.task_signals(self.sql, cur, task)
        self.signals[task] = (now, found)
        return found

    def calibrated_signals(self, cur, task: str, checkpoint: str | None) -> tuple[int, frozenset[str]] | None:
        return self.alerting.calibrated_signals(cur, task, checkpoint)

    def _remember(self, ep: EpisodeState) -> None:
        self.episodes[ep.id] = ep
        self.episodes.move_to_end(ep.id)
        while len(self.episodes) > CACHE_EPISODES:
            self.episodes.popitem(last=False)

    def draft(self, cur, req: Request, episode_id: str) -> EpisodeState | None:
        """The request's draft of an episode (loaded from the database on a cache miss), or None if unknown."""
        if episode_id in req.drafts:
            return req.drafts[episode_id]
        ep = self.episodes.get(episode_id)
        if ep is None:
            ep = statements.load_episode(self.sql, cur, episode_id)
            if ep is None:
                return None
            self._remember(ep)
        draft = ep.draft()
        req.drafts[episode_id] = draft
        return draft

    def apply(self, records: list, principal: Principal,
              idem: tuple[int, str, str] | None = None) -> tuple[dict, Request]:
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
                self._drop_changed(cur, records)
                req = Request(principal)
                apply_records(self, cur, req, records)
                self._write(cur, req)
                result = {"accepted": len(records), "decisions": req.counts["decision"],
                          "targets": req.counts["target"], "outcomes": req.counts["outcome"],
                          "scored": req.scored, "alerts_raised": req.alerts_raised,
                          "alert_state": {ep.id: ep.open_alert_id for ep in req.drafts.values()},
                          "beyond_calibration": [ep.id for ep in req.drafts.values() if ep.beyond_calibration]}
                if idem is not None:
                    statements.store_idempotency(self.sql, cur, idem, result)
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

    def _drop_changed(self, cur, records: list) -> None:
        """Lock the touched episodes' rows and drop cached states that another process has changed since."""
        for episode_id, version in statements.lock_versions(self.sql, cur, sorted({r.episode for r in records})):
            cached = self.episodes.get(episode_id)
            if cached is not None and cached.version != version:
                del self.episodes[episode_id]

    def _write(self, cur, req: Request) -> None:
        compute_scores(req)
        now = self.sql.time(utcnow())
        statements.write_rows(self.sql, cur, req, now)
        for ep in req.drafts.values():
            self.alerting.refresh(cur, req, ep)
            if ep.id in req.ended:
                self.alerting.flag_unpromised(cur, ep)
            if ep.id in req.ended and ep.open_alert_id is not None:   # the outcome resolves its open alert
                statements.resolve_alert(self.sql, cur, ep.open_alert_id, ep.success)
                ep.open_alert_id = None
            statements.update_episode(self.sql, cur, ep, now)

    def idempotent_answer(self, key_id: int, key: str) -> tuple[str, int, dict] | None:
        """(body hash, status, answer) stored for this key's Idempotency-Key, or None."""
        conn = self.engine.raw_connection()
        try:
            cur = conn.cursor()
            found = statements.idempotent_answer(self.sql, cur, key_id, key)
            cur.close()
            if self.sql.dialect != "sqlite":
                conn.rollback()
        finally:
            conn.close()
        return found
