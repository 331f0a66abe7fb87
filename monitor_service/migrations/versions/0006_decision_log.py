"""One append-only decision log (``decision_log``, ``db.DecisionLog``): a row per ingest request and episode
holding its decisions, the late scores of earlier ones and every latent, instead of a row per decision and per
realized latent in two tables with a unique index each. A batch of 64 decisions and their 64 realized latents was
128 rows and 128 index entries; it is one row now (docs/monitor.md, "Tests and benchmark").

Existing rows move with their data: the decisions and realized latents an episode stored at the same instant (one
request wrote them with one timestamp) become one log row with that timestamp, in time order, so every decision
keeps its step, horizon, scores, NMSE and latents and its arrival time. ``decisions`` and ``targets`` are dropped
afterwards. The downgrade unpacks the log into them again.

Revision ID: 0006
Revises: 0005
"""
import json

import numpy as np
import sqlalchemy as sa
from alembic import op

revision = "0006"
down_revision = "0005"
branch_labels = None
depends_on = None

# The log's packing as of this revision (a migration must not change when db.py does).
DECISION_ENTRY = np.dtype([("step", "<i8"), ("horizon", "<i8"), ("nmse", "<f8"), ("nmse_persistence", "<f8")])
Z_HAT, Z_NOW, TARGET = 0, 1, 2
NAN = float("nan")

LOG = sa.table("decision_log", sa.column("episode_id", sa.String), sa.column("decisions", sa.LargeBinary),
               sa.column("scores", sa.JSON(none_as_null=True)), sa.column("rescored", sa.LargeBinary),
               sa.column("dim", sa.Integer), sa.column("entries", sa.LargeBinary), sa.column("latents", sa.LargeBinary),
               sa.column("created_at", sa.DateTime))


def _json(value):
    return value if value is None or isinstance(value, dict) else json.loads(value)


def _log_rows(episode_id: str, decisions: list, targets: list) -> list[dict]:
    """The episode's stored rows grouped by timestamp into log rows (one per latent size within one)."""
    groups: dict = {}
    for step, horizon, nmse, pers, scores, z_hat, z_now, created_at in decisions:
        groups.setdefault(created_at, ([], []))[0].append((step, horizon, nmse, pers, _json(scores), z_hat, z_now))
    for step, z, created_at in targets:
        groups.setdefault(created_at, ([], []))[1].append((step, z))
    rows = []
    for created_at in sorted(groups):
        decs, tgts = groups[created_at]
        latents: dict[int, tuple[list, list]] = {}

        def add(kind: int, step: int, z) -> None:
            z = bytes(z)
            keys, values = latents.setdefault(len(z) // 4, ([], []))
            keys += (kind, step)
            values.append(z)

        for step, _, _, _, _, z_hat, z_now in decs:
            if z_hat is not None:
                add(Z_HAT, step, z_hat)
            if z_now is not None:
                add(Z_NOW, step, z_now)
        for step, z in tgts:
            add(TARGET, step, z)
        scores = {str(d[0]): d[4] for d in decs if d[4] is not None}
        row = {"episode_id": episode_id, "created_at": created_at, "rescored": None, "scores": scores or None,
               "decisions": np.array([(s, -1 if h is None else h, NAN if n is None else n, NAN if p is None else p)
                                      for s, h, n, p, *_ in decs], dtype=DECISION_ENTRY).tobytes() if decs else None,
               "dim": None, "entries": None, "latents": None}
        for dim, (keys, values) in sorted(latents.items()):
            rows.append({**row, "dim": dim, "entries": np.array(keys, dtype="<i8").tobytes(),
                         "latents": b"".join(values)})
            row = {**row, "decisions": None, "scores": None}   # a second latent size: its latents only
        if not latents:
            rows.append(row)
    return rows


def upgrade() -> None:
    op.create_table(
        "decision_log",
        sa.Column("id", sa.Integer, primary_key=True),
        sa.Column("episode_id", sa.String(128), sa.ForeignKey("episodes.id"), nullable=False),
        sa.Column("decisions", sa.LargeBinary, nullable=True),
        sa.Column("scores", sa.JSON, nullable=True),
        sa.Column("rescored", sa.LargeBinary, nullable=True),
        sa.Column("dim", sa.Integer, nullable=True),
        sa.Column("entries", sa.LargeBinary, nullable=True),
        sa.Column("latents", sa.LargeBinary, nullable=True),
        sa.Column("created_at", sa.DateTime, nullable=False),
    )
    op.create_index("ix_decision_log_episode_id", "decision_log", ["episode_id"])
    conn = op.get_bind()
    if conn.dialect.name == "postgresql":   # float32 vectors do not compress: store them without trying
        op.execute("ALTER TABLE decision_log ALTER COLUMN latents SET STORAGE EXTERNAL")
    episodes = [r[0] for r in conn.execute(sa.text(
        "SELECT episode_id FROM decisions UNION SELECT episode_id FROM targets ORDER BY 1"))]
    for episode_id in episodes:   # one episode's rows in memory at a time
        decisions = conn.execute(sa.text(
            "SELECT step, horizon, nmse, nmse_persistence, scores, z_hat, z_now, created_at FROM decisions "
            "WHERE episode_id = :e ORDER BY step").columns(created_at=sa.DateTime), {"e": episode_id}).all()
        targets = conn.execute(sa.text("SELECT step, z, created_at FROM targets WHERE episode_id = :e ORDER BY step")
                               .columns(created_at=sa.DateTime), {"e": episode_id}).all()
        conn.execute(LOG.insert(), _log_rows(episode_id, decisions, targets))
    op.drop_table("targets")
    op.drop_table("decisions")


def downgrade() -> None:
    op.create_table(
        "decisions",
        sa.Column("id", sa.Integer, primary_key=True),
        sa.Column("episode_id", sa.String(128), sa.ForeignKey("episodes.id"), nullable=False),
        sa.Column("step", sa.Integer, nullable=False),
        sa.Column("horizon", sa.Integer, nullable=True),
        sa.Column("target_step", sa.Integer, nullable=True),
        sa.Column("z_hat", sa.LargeBinary, nullable=True),
        sa.Column("nmse", sa.Float, nullable=True),
        sa.Column("created_at", sa.DateTime, nullable=False),
        sa.Column("z_now", sa.LargeBinary, nullable=True),
        sa.Column("nmse_persistence", sa.Float, nullable=True),
        sa.Column("scores", sa.JSON, nullable=True),
        sa.UniqueConstraint("episode_id", "step", name="uq_decision_episode_step"),
    )
    op.create_table(
        "targets",
        sa.Column("id", sa.Integer, primary_key=True),
        sa.Column("episode_id", sa.String(128), sa.ForeignKey("episodes.id"), nullable=False),
        sa.Column("step", sa.Integer, nullable=False),
        sa.Column("z", sa.LargeBinary, nullable=False),
        sa.Column("created_at", sa.DateTime, nullable=False),
        sa.UniqueConstraint("episode_id", "step", name="uq_target_episode_step"),
    )
    conn = op.get_bind()
    decisions_table = sa.table("decisions", *(sa.column(c) for c in (
        "episode_id", "step", "horizon", "target_step", "z_hat", "nmse", "z_now", "nmse_persistence")),
        sa.column("scores", sa.JSON(none_as_null=True)), sa.column("created_at", sa.DateTime))
    targets_table = sa.table("targets", *(sa.column(c) for c in ("episode_id", "step", "z")),
                             sa.column("created_at", sa.DateTime))
    episodes = [r[0] for r in conn.execute(sa.text("SELECT DISTINCT episode_id FROM decision_log ORDER BY 1"))]
    for episode_id in episodes:
        decisions: dict[int, dict] = {}
        targets = []
        rows = conn.execute(sa.text("SELECT decisions, scores, rescored, dim, entries, latents, created_at FROM "
                                    "decision_log WHERE episode_id = :e ORDER BY id").columns(created_at=sa.DateTime),
                            {"e": episode_id})
        for packed, scores, rescored, dim, entries, latents, created_at in rows:
            scores = _json(scores) or {}
            if packed is not None:
                for step, horizon, nmse, pers in np.frombuffer(packed, dtype=DECISION_ENTRY).tolist():
                    decisions[step] = {"episode_id": episode_id, "step": step,
                                       "horizon": None if horizon < 0 else horizon,
                                       "target_step": None if horizon < 0 else step + horizon,
                                       "nmse": None if nmse != nmse else nmse,
                                       "nmse_persistence": None if pers != pers else pers,
                                       "scores": scores.get(str(step)), "z_hat": None, "z_now": None,
                                       "created_at": created_at}
            if rescored is not None:
                for step, nmse, pers in np.frombuffer(rescored, dtype=[("s", "<i8"), ("n", "<f8"),
                                                                       ("p", "<f8")]).tolist():
                    decisions[step]["nmse"], decisions[step]["nmse_persistence"] = nmse, None if pers != pers else pers
            if entries is not None:
                size, latents = dim * 4, bytes(latents)
                for i, (kind, step) in enumerate(np.frombuffer(entries, dtype="<i8").reshape(-1, 2).tolist()):
                    z = latents[i * size:(i + 1) * size]
                    if kind == TARGET:
                        targets.append({"episode_id": episode_id, "step": step, "z": z, "created_at": created_at})
                    else:
                        decisions[step]["z_hat" if kind == Z_HAT else "z_now"] = z
        if decisions:
            conn.execute(decisions_table.insert(), list(decisions.values()))
        if targets:
            conn.execute(targets_table.insert(), targets)
    op.drop_index("ix_decision_log_episode_id", table_name="decision_log")
    op.drop_table("decision_log")
