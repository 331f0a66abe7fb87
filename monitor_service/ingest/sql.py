"""The ingest path's statements: raw DB-API SQL in the database's own parameter style, a few per request.

SQLAlchemy's ORM would cost more per record than the rest of the request (``docs/monitor.md``, "Tests and
benchmark"); the schema itself stays SQLAlchemy's (``db.py``, migrations).

A request appends one ``decision_log`` row per episode it touched (``db.DecisionLog``): its new decisions, the
late scores of earlier ones and its latents, packed, where each record was a row of an indexed table before. Reading
an episode back (a resend to compare, an episode resumed by another process) folds its log rows.
"""
from __future__ import annotations

import json

import numpy as np

from monitor_service import scoring
from monitor_service.db import TARGET, Z_HAT, Z_NOW, fold_decisions, pack_decisions, pack_rescored, utcnow
from monitor_service.ingest.state import Dec, EpisodeState, Request, StaleState, Tgt

EPISODE_COLUMNS = ("id, task, robot, checkpoint, group_name, held_out, success, length, version, n_decisions, "
                   "n_scored, last_evaluated_step, over_count, under_count, open_alert_id, early_score, "
                   "running_score, risk_score, alert_note, risk_threshold, calibrated_decisions, "
                   "beyond_calibration, late_decisions, early_revisions, signal_state, ended_at")


class Sql:
    """Statements in the database's own parameter style (sqlite3: ?, psycopg 3: %s), on a raw DB-API cursor.
    psycopg 3 binds parameters on the server and sends bytes in binary: a request's latents travel as they are,
    not as an escaped literal the server has to parse."""

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

    def insert_one(self, cur, table: str, columns: str, row: tuple) -> None:
        marks = ", ".join([self.mark] * (columns.count(",") + 1))
        cur.execute(f"INSERT INTO {table} ({columns}) VALUES ({marks})", row)

    def time(self, value):
        """A naive-UTC datetime as this database stores it (SQLite: SQLAlchemy's text format)."""
        return value.strftime("%Y-%m-%d %H:%M:%S.%f") if self.dialect == "sqlite" else value


# ---------------------------------------------------------------------------------------------------- reading

def lock_versions(sql: Sql, cur, episode_ids: list[str]) -> list[tuple[str, int]]:
    """(id, version) of the given episodes, their rows locked for this transaction (PostgreSQL: FOR UPDATE, in
    id order; SQLite: the transaction is a writer already)."""
    marks = ", ".join([sql.mark] * len(episode_ids))
    lock = "" if sql.dialect == "sqlite" else " FOR UPDATE"
    cur.execute(f"SELECT id, version FROM episodes WHERE id IN ({marks}) ORDER BY id{lock}", episode_ids)
    return cur.fetchall()


class StoredEpisode:
    """An episode's log rows as stored: its decisions by step and its latents by (kind, step)."""

    def __init__(self, sql: Sql, cur, episode_id: str):
        cur.execute(sql.q("SELECT decisions, scores, rescored, dim, entries, latents FROM decision_log "
                          "WHERE episode_id = ? ORDER BY id"), (episode_id,))
        rows = cur.fetchall()
        self.decisions = {d["step"]: d for d in fold_decisions([r[:3] for r in rows])}
        self.latents: dict[tuple[int, int], bytes] = {}
        for *_, dim, entries, latents in rows:
            if entries is None:
                continue
            size, view = dim * 4, memoryview(latents)
            for i, (kind, step) in enumerate(np.frombuffer(entries, dtype="<i8").reshape(-1, 2).tolist()):
                self.latents[kind, step] = bytes(view[i * size:(i + 1) * size])


def load_episode(sql: Sql, cur, episode_id: str) -> EpisodeState | None:
    """An episode's state from its rows (decision latents kept only while unscored), or None if unknown."""
    cur.execute(sql.q(f"SELECT {EPISODE_COLUMNS} FROM episodes WHERE id = ?"), (episode_id,))
    row = cur.fetchone()
    if row is None:
        return None
    ep = EpisodeState(row[0], row[1], row[2], row[3], row[4], bool(row[5]),
                      None if row[6] is None else bool(row[6]), row[7], row[8], row[9], row[10], row[11],
                      row[12], row[13], row[14], row[15], row[16], row[17], row[18], row[19], row[20],
                      bool(row[21]), late_decisions=row[22], early_revisions=row[23],
                      signal_state=row[24] if row[24] is None or isinstance(row[24], dict) else json.loads(row[24]),
                      ended=row[25] is not None)
    stored = StoredEpisode(sql, cur, episode_id)
    for step, dec in stored.decisions.items():
        horizon, nmse, pers, scores = dec["horizon"], dec["nmse"], dec["nmse_persistence"], dec["scores"]
        d = Dec(horizon, nmse, pers, scores=scores)
        if horizon is not None and nmse is None:   # latents waiting for their target
            d.z_hat, d.z_now = stored.latents[Z_HAT, step], stored.latents.get((Z_NOW, step))
            ep.unscored.add(step)
        elif nmse is not None:
            ep.scored.append((step, nmse))
            ratio = scoring.nmse_ratio_or_none(nmse, pers)
            if ratio is not None:   # the service's own signal, derived again (not stored)
                ep.series.setdefault(scoring.RATIO, []).append((step, ratio))
        for name, value in (scores or {}).items():
            if name != scoring.RATIO:   # a score sent under that name before the service computed it: not the signal
                ep.series.setdefault(name, []).append((step, value))
        ep.decisions[step] = d
    aimed = {s + d.horizon for s, d in ep.decisions.items() if d.horizon is not None}
    for (kind, step), z in stored.latents.items():
        if kind == TARGET:
            ep.targets[step] = Tgt(None if step in aimed else z)
    ep.count_gaps()
    return ep


def stored_episode(sql: Sql, cur, req: Request, episode_id: str) -> StoredEpisode:
    """The episode as stored, read once per request (a resent batch compares many records)."""
    found = req.stored.get(episode_id)
    if found is None:
        found = req.stored[episode_id] = StoredEpisode(sql, cur, episode_id)
    return found


def stored_decision(sql: Sql, cur, req: Request, episode_id: str, step: int) -> tuple | None:
    """(horizon, z_hat, z_now, scores) of a stored decision (to recognise a resend), or None."""
    stored = stored_episode(sql, cur, req, episode_id)
    dec = stored.decisions.get(step)
    if dec is None:
        return None
    return dec["horizon"], stored.latents.get((Z_HAT, step)), stored.latents.get((Z_NOW, step)), dec["scores"]


def target_latent(sql: Sql, cur, req: Request, episode_id: str, step: int) -> bytes | None:
    """A stored realized latent (dropped from memory once a decision used it)."""
    return stored_episode(sql, cur, req, episode_id).latents.get((TARGET, step))


def task_signals(sql: Sql, cur, task: str) -> frozenset[str] | None:
    """The named signals registered for a task, or None when the task is not registered."""
    cur.execute(sql.q("SELECT signals FROM tasks WHERE name = ?"), (task,))
    row = cur.fetchone()
    if row is None:
        return None
    signals = row[0] if row[0] is None or isinstance(row[0], list) else json.loads(row[0])
    return frozenset(signals or ())


def task_latent_dim(sql: Sql, cur, task: str, dim: int) -> tuple[int, bool] | None:
    """(the task's latent size, whether this transaction fixed it): the first latent fixes it, and a concurrent
    first latent cannot fix another. None when the task is not registered."""
    cur.execute(sql.q("SELECT latent_dim FROM tasks WHERE name = ?"), (task,))
    row = cur.fetchone()
    if row is None:
        return None
    if row[0] is not None:
        return row[0], False
    cur.execute(sql.q("UPDATE tasks SET latent_dim = ? WHERE name = ? AND latent_dim IS NULL"), (dim, task))
    cur.execute(sql.q("SELECT latent_dim FROM tasks WHERE name = ?"), (task,))
    return cur.fetchone()[0], True


def active_calibration(sql: Sql, cur, task: str, checkpoint: str | None) -> tuple[int | None, dict | None]:
    """(id, result) of the active calibration of a checkpoint, else of its task; (None, None) without one."""
    for ckpt in ([checkpoint] if checkpoint is not None else []) + [None]:
        cond = "checkpoint IS NULL" if ckpt is None else "checkpoint = ?"
        cur.execute(sql.q(f"SELECT id, result FROM calibrations WHERE task = ? AND {cond} AND active = ?"
                          " ORDER BY id DESC"), (task, True) if ckpt is None else (task, ckpt, True))
        row = cur.fetchone()
        if row is not None:   # JSON column: text on SQLite, already decoded by psycopg
            return row[0], row[1] if isinstance(row[1], dict) else json.loads(row[1])
    return None, None


def idempotent_answer(sql: Sql, cur, key_id: int, key: str) -> tuple[str, int, dict] | None:
    """(body hash, status, answer) stored for this key's Idempotency-Key, or None."""
    cur.execute(sql.q("SELECT request_hash, status_code, response FROM idempotency_keys "
                      "WHERE api_key_id = ? AND key = ?"), (key_id, key))
    row = cur.fetchone()
    if row is None:
        return None
    return row[0], row[1], row[2] if isinstance(row[2], dict) else json.loads(row[2])


# ---------------------------------------------------------------------------------------------------- writing

def insert_alert(sql: Sql, cur, ep: EpisodeState, cal_id: int, step: int, value: float, threshold: float,
                 note: str, beyond: bool, webhook_urls: list[str], signals: str = "nmse",
                 no_promise: bool = False) -> int:
    """A raised alert (and a pending delivery per webhook URL); returns its id. ``no_promise``: the episode can
    still end at a length whose false-alert rate the calibration does not promise (the note says which)."""
    now = sql.time(utcnow())
    cur.execute(sql.q(
        "INSERT INTO alerts (episode_id, task, robot, step, score, threshold, calibration_id, state, note, "
        "raised_at, beyond_calibration, signals, no_promise) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?) "
        "RETURNING id"),
        (ep.id, ep.task, ep.robot, step, value, threshold, cal_id, "open", note[:512], now, beyond, signals,
         no_promise))
    alert_id = cur.fetchone()[0]
    if webhook_urls:
        cur.executemany(sql.q(
            "INSERT INTO webhook_deliveries (alert_id, url, status, attempts, next_attempt_at, last_error) "
            "VALUES (?, ?, ?, ?, ?, ?)"), [(alert_id, url, "pending", 0, now, "") for url in webhook_urls])
    return alert_id


def flag_unpromised(sql: Sql, cur, episode_id: str, why: str) -> None:
    """The episode's alerts not yet flagged: no false-alert promise covers them, and why (in the note)."""
    cur.execute(sql.q("UPDATE alerts SET no_promise = ?, note = substr(note || ?, 1, 512) "
                      "WHERE episode_id = ? AND no_promise = ?"), (True, f"; {why}", episode_id, False))


def clear_alert(sql: Sql, cur, alert_id: int) -> None:
    cur.execute(sql.q("UPDATE alerts SET state = ?, cleared_at = ? WHERE id = ?"),
                ("cleared", sql.time(utcnow()), alert_id))


def resolve_alert(sql: Sql, cur, alert_id: int, success: bool) -> None:
    """The episode's outcome arrived while the alert was open or acknowledged: a false alert on a success, a
    true one on a failure."""
    cur.execute(sql.q("UPDATE alerts SET state = ?, resolved_at = ?, resolution = ? WHERE id = ?"),
                ("resolved", sql.time(utcnow()), "success" if success else "failure", alert_id))


def write_rows(sql: Sql, cur, req: Request, now) -> None:
    """The request's new episodes, and one decision-log row per episode: its new decisions, the late scores of
    stored ones, its latents."""
    q = sql.q
    logs: dict[str, tuple[list, dict, list, list, list]] = {}   # decisions, scores, rescored, keys, latents

    def log(eid: str) -> tuple[list, dict, list, list, list]:
        entry = logs.get(eid)
        if entry is None:
            entry = logs[eid] = ([], {}, [], [], [])
        return entry

    for ep in req.drafts.values():
        if ep.new:
            cur.execute(q(
                "INSERT INTO episodes (id, task, robot, checkpoint, group_name, held_out, n_decisions, n_scored, "
                "last_evaluated_step, over_count, under_count, alert_note, started_at, updated_at, version) "
                "VALUES (?, ?, ?, ?, ?, ?, 0, 0, -1, 0, 0, '', ?, ?, 0)"),
                (ep.id, ep.task, ep.robot, ep.checkpoint, ep.group, ep.held_out, now, now))
    for eid, step in req.new_decisions:
        d = req.drafts[eid].decisions[step]
        decisions, scores, _, keys, latents = log(eid)
        decisions.append((step, d.horizon, d.nmse, d.nmse_persistence))
        if d.scores is not None:
            scores[str(step)] = d.scores
        if d.z_hat is not None:
            keys += (Z_HAT, step)
            latents.append(d.z_hat)
            if d.z_now is not None:
                keys += (Z_NOW, step)
                latents.append(d.z_now)
    for eid, step in req.scored_stored:
        d = req.drafts[eid].decisions[step]
        log(eid)[2].append((step, d.nmse, d.nmse_persistence))
    for eid, step, z in req.new_targets:
        _, _, _, keys, latents = log(eid)
        keys += (TARGET, step)
        latents.append(z)
    for eid, (decisions, scores, rescored, keys, latents) in logs.items():
        sql.insert_one(cur, "decision_log",
                       "episode_id, decisions, scores, rescored, dim, entries, latents, created_at",
                       (eid, pack_decisions(decisions) if decisions else None, json.dumps(scores) if scores else None,
                        pack_rescored(rescored) if rescored else None, len(latents[0]) // 4 if latents else None,
                        np.array(keys, dtype="<i8").tobytes() if keys else None, b"".join(latents) if latents else None,
                        now))


def update_episode(sql: Sql, cur, ep: EpisodeState, now) -> None:
    """Write an episode's state under its version counter; StaleState when another process changed it."""
    cur.execute(sql.q(
        "UPDATE episodes SET version = ?, group_name = ?, held_out = ?, success = ?, length = ?, "
        "n_decisions = ?, n_scored = ?, last_evaluated_step = ?, over_count = ?, under_count = ?, "
        "open_alert_id = ?, early_score = ?, running_score = ?, risk_score = ?, alert_note = ?, "
        "risk_threshold = ?, calibrated_decisions = ?, beyond_calibration = ?, gaps = ?, gap_steps = ?, "
        "late_decisions = ?, early_revisions = ?, signal_state = ?, "
        "updated_at = ?, ended_at = COALESCE(ended_at, ?) WHERE id = ? AND version = ?"),
        (ep.version + 1, ep.group, ep.held_out, ep.success, ep.length, ep.n_decisions, ep.n_scored,
         ep.last_evaluated_step, ep.over_count, ep.under_count, ep.open_alert_id, ep.early_score,
         ep.running_score, ep.risk_score, ep.alert_note[:512], ep.risk_threshold, ep.calibrated_decisions,
         ep.beyond_calibration, ep.gaps, json.dumps(ep.gap_steps) if ep.gap_steps else None, ep.late_decisions,
         ep.early_revisions, None if ep.signal_state is None else json.dumps(ep.signal_state), now,
         now if ep.ended else None, ep.id, ep.version))
    if cur.rowcount != 1:
        raise StaleState(f"episode {ep.id!r} changed in another process")
    ep.version += 1


def store_idempotency(sql: Sql, cur, idem: tuple[int, str, str], result: dict) -> None:
    key_id, key, body_hash = idem
    cur.execute(sql.q("INSERT INTO idempotency_keys (api_key_id, key, request_hash, status_code, response, "
                      "created_at) VALUES (?, ?, ?, ?, ?, ?)"),
                (key_id, key, body_hash, 200, json.dumps(result), sql.time(utcnow())))
