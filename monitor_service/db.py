"""Storage: SQLAlchemy 2 models, the engine (SQLite in WAL mode or PostgreSQL), the migration runner, and the
decision log's packing (``DecisionLog``)."""
from __future__ import annotations

import datetime as dt
import json
import re
from pathlib import Path

import numpy as np
from sqlalchemy import (
    JSON,
    Boolean,
    DateTime,
    Float,
    ForeignKey,
    Integer,
    LargeBinary,
    String,
    UniqueConstraint,
    create_engine,
    event,
    false,
    select,
    text,
)
from sqlalchemy.engine import Engine, make_url
from sqlalchemy.exc import ArgumentError
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, sessionmaker

MIGRATIONS_DIR = Path(__file__).parent / "migrations"


def utcnow() -> dt.datetime:
    """Timezone-aware now in UTC (stored as naive UTC for SQLite portability)."""
    return dt.datetime.now(dt.timezone.utc).replace(tzinfo=None)


class Base(DeclarativeBase):
    pass


class ApiKey(Base):
    __tablename__ = "api_keys"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    name: Mapped[str] = mapped_column(String(128), unique=True)
    key_hash: Mapped[str] = mapped_column(String(64), unique=True)
    role: Mapped[str] = mapped_column(String(16))
    robot: Mapped[str | None] = mapped_column(String(128), nullable=True)
    created_at: Mapped[dt.datetime] = mapped_column(DateTime, default=utcnow)
    revoked_at: Mapped[dt.datetime | None] = mapped_column(DateTime, nullable=True)


class Task(Base):
    __tablename__ = "tasks"
    name: Mapped[str] = mapped_column(String(128), primary_key=True)
    latent_dim: Mapped[int | None] = mapped_column(Integer, nullable=True)
    description: Mapped[str] = mapped_column(String(512), default="")
    signals: Mapped[list | None] = mapped_column(JSON, nullable=True)   # named per-decision scores robots may send
    created_at: Mapped[dt.datetime] = mapped_column(DateTime, default=utcnow)


class Episode(Base):
    __tablename__ = "episodes"
    id: Mapped[str] = mapped_column(String(128), primary_key=True)
    task: Mapped[str] = mapped_column(ForeignKey("tasks.name"), index=True)
    robot: Mapped[str] = mapped_column(String(128), index=True)
    checkpoint: Mapped[str | None] = mapped_column(String(256), nullable=True)
    group: Mapped[str | None] = mapped_column("group_name", String(128), nullable=True)
    held_out: Mapped[bool] = mapped_column(Boolean, default=False)
    success: Mapped[bool | None] = mapped_column(Boolean, nullable=True)
    early_score: Mapped[float | None] = mapped_column(Float, nullable=True)
    running_score: Mapped[float | None] = mapped_column(Float, nullable=True)
    n_decisions: Mapped[int] = mapped_column(Integer, default=0)
    n_scored: Mapped[int] = mapped_column(Integer, default=0)
    last_evaluated_step: Mapped[int] = mapped_column(Integer, default=-1)
    over_count: Mapped[int] = mapped_column(Integer, default=0)
    under_count: Mapped[int] = mapped_column(Integer, default=0)
    open_alert_id: Mapped[int | None] = mapped_column(Integer, nullable=True)
    alert_note: Mapped[str] = mapped_column(String(512), default="")
    started_at: Mapped[dt.datetime] = mapped_column(DateTime, default=utcnow)
    updated_at: Mapped[dt.datetime] = mapped_column(DateTime, default=utcnow, index=True)
    ended_at: Mapped[dt.datetime | None] = mapped_column(DateTime, nullable=True)
    length: Mapped[int | None] = mapped_column(Integer, nullable=True)  # env steps, from the outcome
    risk_score: Mapped[float | None] = mapped_column(Float, nullable=True)  # the calibrated rule's latest statistic
    # bumped by every ingest write: a server process's cached state of the episode is current when it matches
    version: Mapped[int] = mapped_column(Integer, default=0, server_default="0")
    risk_threshold: Mapped[float | None] = mapped_column(Float, nullable=True)   # T(i) the risk was judged against
    calibrated_decisions: Mapped[int | None] = mapped_column(Integer, nullable=True)   # the rule's longest length
    beyond_calibration: Mapped[bool] = mapped_column(Boolean, default=False, server_default=false())
    gaps: Mapped[int] = mapped_column(Integer, default=0, server_default="0")   # decision indices still missing
    gap_steps: Mapped[list | None] = mapped_column(JSON, nullable=True)         # their steps (the first ones)
    late_decisions: Mapped[int] = mapped_column(Integer, default=0, server_default="0")
    early_revisions: Mapped[int] = mapped_column(Integer, default=0, server_default="0")
    signal_state: Mapped[dict | None] = mapped_column(JSON, nullable=True)      # per-signal rule state


class DecisionLog(Base):
    """An episode's decisions, their scores and every latent, append-only: one row per ingest request that brought
    records of the episode (migration 0006; before it, one row per decision and per realized latent in two tables
    with a unique index each).

    - ``decisions``: the request's new decisions, ``DECISION_ENTRY`` records (horizon -1: a decision that sent
      scores only; NaN: not scored yet), and ``scores`` their named scores ({step: {signal: value}}) when any;
    - ``rescored``: decisions of earlier rows scored by this request's realized latents, ``RESCORE_ENTRY``
      records; a decision's scores are its entry's, overwritten by later rows' rescored entries;
    - ``entries`` and ``latents``: the latents it brought, (kind, step) as little-endian int64 pairs per latent
      (kind ``Z_HAT``, ``Z_NOW`` or ``TARGET``) and the float32 little-endian vectors of ``dim`` values in the same
      order. Only the ingest path reads latents (a resend to compare, an episode resumed by another process).

    ``read_decisions`` folds the rows into each episode's decisions; the unique index per decision step is gone:
    the ingest path refuses a second decision at a step under the episode row's lock and version counter."""
    __tablename__ = "decision_log"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    episode_id: Mapped[str] = mapped_column(ForeignKey("episodes.id"), index=True)
    decisions: Mapped[bytes | None] = mapped_column(LargeBinary, nullable=True)
    scores: Mapped[dict | None] = mapped_column(JSON, nullable=True)
    rescored: Mapped[bytes | None] = mapped_column(LargeBinary, nullable=True)
    dim: Mapped[int | None] = mapped_column(Integer, nullable=True)
    entries: Mapped[bytes | None] = mapped_column(LargeBinary, nullable=True)
    latents: Mapped[bytes | None] = mapped_column(LargeBinary, nullable=True)
    created_at: Mapped[dt.datetime] = mapped_column(DateTime, default=utcnow)


DECISION_ENTRY = np.dtype([("step", "<i8"), ("horizon", "<i8"), ("nmse", "<f8"), ("nmse_persistence", "<f8")])
RESCORE_ENTRY = np.dtype([("step", "<i8"), ("nmse", "<f8"), ("nmse_persistence", "<f8")])
Z_HAT, Z_NOW, TARGET = 0, 1, 2   # what a latent of a log row is: a decision's z_hat, its z_now, a realized z
NAN = float("nan")


def pack_decisions(rows: list[tuple[int, int | None, float | None, float | None]]) -> bytes:
    """(step, horizon, nmse, nmse_persistence) rows as ``DECISION_ENTRY`` bytes (None: -1 or NaN)."""
    return np.array([(s, -1 if h is None else h, NAN if n is None else n, NAN if p is None else p)
                     for s, h, n, p in rows], dtype=DECISION_ENTRY).tobytes()


def pack_rescored(rows: list[tuple[int, float, float | None]]) -> bytes:
    return np.array([(s, n, NAN if p is None else p) for s, n, p in rows], dtype=RESCORE_ENTRY).tobytes()


def fold_decisions(rows) -> list[dict]:
    """An episode's decisions in step order from its log rows' (decisions, scores, rescored) in row order:
    {"step", "horizon", "target_step", "nmse", "nmse_persistence", "scores"} each (None where absent)."""
    found: dict[int, dict] = {}
    for decisions, scores, rescored in rows:
        if scores is not None and not isinstance(scores, dict):   # JSON: text on SQLite, decoded by psycopg
            scores = json.loads(scores)
        if decisions is not None:
            for step, horizon, nmse, pers in np.frombuffer(decisions, dtype=DECISION_ENTRY).tolist():
                found[step] = {"step": step, "horizon": None if horizon < 0 else horizon,
                               "target_step": None if horizon < 0 else step + horizon,
                               "nmse": None if nmse != nmse else nmse,
                               "nmse_persistence": None if pers != pers else pers,
                               "scores": None if scores is None else scores.get(str(step))}
        if rescored is not None:
            for step, nmse, pers in np.frombuffer(rescored, dtype=RESCORE_ENTRY).tolist():
                found[step]["nmse"], found[step]["nmse_persistence"] = nmse, None if pers != pers else pers
    return [found[s] for s in sorted(found)]


def read_decisions(session, episode_ids: list[str]) -> dict[str, list[dict]]:
    """Every decision of the given episodes (``fold_decisions``), by episode id; a session or a connection."""
    by_episode: dict[str, list] = {e: [] for e in episode_ids}
    for start in range(0, len(episode_ids), 500):   # bounded IN lists
        q = (select(DecisionLog.episode_id, DecisionLog.decisions, DecisionLog.scores, DecisionLog.rescored)
             .where(DecisionLog.episode_id.in_(episode_ids[start:start + 500])).order_by(DecisionLog.id))
        for episode_id, decisions, scores, rescored in session.execute(q):
            by_episode[episode_id].append((decisions, scores, rescored))
    return {e: fold_decisions(rows) for e, rows in by_episode.items()}


class CalibrationRow(Base):
    __tablename__ = "calibrations"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    task: Mapped[str] = mapped_column(ForeignKey("tasks.name"), index=True)
    checkpoint: Mapped[str | None] = mapped_column(String(256), nullable=True)
    active: Mapped[bool] = mapped_column(Boolean, default=True)
    rule: Mapped[str] = mapped_column("threshold_rule", String(16))  # running | band (monitor_service/rules.py)
    threshold: Mapped[float | None] = mapped_column(Float, nullable=True)
    auroc: Mapped[float] = mapped_column(Float)
    result: Mapped[dict] = mapped_column(JSON)
    created_at: Mapped[dt.datetime] = mapped_column(DateTime, default=utcnow)


class Alert(Base):
    __tablename__ = "alerts"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    episode_id: Mapped[str] = mapped_column(ForeignKey("episodes.id"), index=True)
    task: Mapped[str] = mapped_column(String(128), index=True)
    robot: Mapped[str] = mapped_column(String(128))
    step: Mapped[int] = mapped_column(Integer)
    score: Mapped[float] = mapped_column(Float)
    threshold: Mapped[float] = mapped_column(Float)
    calibration_id: Mapped[int] = mapped_column(Integer)
    # open -> acknowledged (an operator took it) -> resolved (the episode's outcome arrived); open or acknowledged
    # -> cleared (the rule's statistic fell back below its hysteresis level while the episode ran)
    state: Mapped[str] = mapped_column(String(16), default="open", index=True)
    acknowledged_by: Mapped[str | None] = mapped_column(String(128), nullable=True)
    acknowledged_at: Mapped[dt.datetime | None] = mapped_column(DateTime, nullable=True)
    note: Mapped[str] = mapped_column(String(512), default="")
    raised_at: Mapped[dt.datetime] = mapped_column(DateTime, default=utcnow)
    cleared_at: Mapped[dt.datetime | None] = mapped_column(DateTime, nullable=True)
    resolved_at: Mapped[dt.datetime | None] = mapped_column(DateTime, nullable=True)
    resolution: Mapped[str | None] = mapped_column(String(16), nullable=True)   # failure (true) or success (false)
    beyond_calibration: Mapped[bool] = mapped_column(Boolean, default=False, server_default=false())
    signals: Mapped[str] = mapped_column(String(512), default="nmse", server_default="nmse")
    # the episode could still end at a length the calibration holds too few successes of to promise alpha
    no_promise: Mapped[bool] = mapped_column(Boolean, default=False, server_default=false())


class WebhookDelivery(Base):
    __tablename__ = "webhook_deliveries"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    alert_id: Mapped[int] = mapped_column(ForeignKey("alerts.id"), index=True)
    url: Mapped[str] = mapped_column(String(1024))
    status: Mapped[str] = mapped_column(String(16), default="pending", index=True)  # pending, delivered, failed
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    next_attempt_at: Mapped[dt.datetime] = mapped_column(DateTime, default=utcnow)
    claimed_until: Mapped[dt.datetime | None] = mapped_column(DateTime, nullable=True)
    last_error: Mapped[str] = mapped_column(String(1024), default="")


class IdempotencyKey(Base):
    __tablename__ = "idempotency_keys"
    __table_args__ = (UniqueConstraint("api_key_id", "key", name="uq_idempotency_owner_key"),)
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    api_key_id: Mapped[int] = mapped_column(Integer)
    key: Mapped[str] = mapped_column(String(128))
    request_hash: Mapped[str] = mapped_column(String(64))
    status_code: Mapped[int] = mapped_column(Integer)
    response: Mapped[dict] = mapped_column(JSON)
    created_at: Mapped[dt.datetime] = mapped_column(DateTime, default=utcnow)


def sqlite_file(url: str) -> Path | None:
    """The file of an SQLite URL (None for other databases and for an in-memory one)."""
    parsed = make_url(url)
    if parsed.get_backend_name() != "sqlite" or parsed.database in (None, "", ":memory:"):
        return None
    return Path(parsed.database)


_URL_USER_SECRET = re.compile(r"(//[^/@:?#]*:)[^/@?#]*@")
_URL_QUERY_SECRET = re.compile(r"(?i)([?&](?:ssl)?password=)[^&#]*")


def redacted(url: str) -> str:
    """A database URL as it may be printed: a password, in the user part or in the query string, as ***."""
    return _URL_QUERY_SECRET.sub(r"\1***", _URL_USER_SECRET.sub(r"\1***@", url))


PG_DRIVER = "psycopg"   # psycopg 3: binary parameters (docs/monitor.md, "Tests and benchmark")


def postgres_url(url: str) -> str:
    """A PostgreSQL URL without a driver (``postgresql://`` or ``postgres://``, libpq's own forms) as psycopg 3's;
    others unchanged."""
    for scheme in ("postgresql://", "postgres://"):
        if url.startswith(scheme):
            return f"postgresql+{PG_DRIVER}://" + url[len(scheme):]
    return url


def check_database_url(url: str, *, create: bool = False) -> None:
    """Refuse, with one line naming the fix, a URL that cannot be parsed, an SQLite file in a folder that does not
    exist, an SQLite file that does not exist (unless ``create``: `jepa-monitor db upgrade` or `serve --create`;
    otherwise a mistyped name would serve a fresh, empty database) and a PostgreSQL URL for another driver than
    psycopg 3 or whose driver is missing (``postgresql://`` without a driver means psycopg 3)."""
    try:
        parsed = make_url(postgres_url(url))
    except ArgumentError:
        raise ValueError(f"database URL {redacted(url)!r} is not a valid URL; use sqlite:///relative.db, "
                         "sqlite:////absolute/path.db or postgresql+psycopg://user:password@host/database") from None
    backend = parsed.get_backend_name()
    if backend == "sqlite":
        path = sqlite_file(url)
        if path is None:   # make_engine's pool needs a file, and an in-memory database ends with its process
            raise ValueError(f"database URL {url!r} is an in-memory SQLite database, which keeps nothing once the "
                             "process ends; give a file: sqlite:///jepa_monitor.db or sqlite:////absolute/path.db")
        if not path.parent.is_dir():
            raise ValueError(f"the folder {path.parent} of the database {path} does not exist; create it "
                             f"(mkdir -p {path.parent}) or fix the database URL {url!r}")
        if not create and not path.exists():
            raise ValueError(f"no database at {path}; create it with `jepa-monitor --database-url {url} db upgrade` "
                             "(or `jepa-monitor serve --create`), or fix the path if it is mistyped")
        return
    if backend != "postgresql":
        raise ValueError(f"database URL {redacted(url)!r} is neither SQLite nor PostgreSQL; use sqlite:///path.db or "
                         "postgresql+psycopg://user@host/db")
    driver = parsed.get_driver_name()
    if driver != PG_DRIVER:
        why = (" (latents go as binary parameters: about a quarter of the database's CPU per batch of psycopg2's "
               "escaped literals)") if driver == "psycopg2" else " (synchronous, with binary parameters)"
        fixed = redacted(parsed.set(drivername="postgresql+" + PG_DRIVER).render_as_string(hide_password=False))
        raise ValueError(f"the database URL {parsed.drivername}:// names the {driver} driver; the monitor talks to "
                         f"PostgreSQL through psycopg 3{why}. Write {fixed}")
    try:
        parsed.get_dialect().import_dbapi()
    except ImportError as exc:
        raise ValueError(f"the database URL {parsed.drivername}:// needs the {exc.name or 'its'} driver, which is not "
                         "installed; pip install 'psycopg[binary]' (it comes with the monitor extra)") from None


def make_engine(url: str) -> Engine:
    """Create the engine; SQLite gets WAL, a busy timeout and BEGIN IMMEDIATE so concurrent writers queue."""
    if url.startswith("sqlite"):
        # a pool as large as the request thread pool: connections are reused, never opened per request (the
        # PRAGMAs below cost more than the request's own statements)
        engine = create_engine(url, connect_args={"check_same_thread": False, "timeout": 30}, pool_size=40,
                               max_overflow=10)

        @event.listens_for(engine, "connect")
        def _sqlite_pragmas(dbapi_conn, _record):
            # pysqlite's own transaction handling would defer BEGIN; we issue BEGIN IMMEDIATE ourselves (below)
            # so a reader never has to upgrade to a writer lock, the cause of "database is locked" under load.
            dbapi_conn.isolation_level = None
            cur = dbapi_conn.cursor()
            cur.execute("PRAGMA journal_mode=WAL")
            cur.execute("PRAGMA synchronous=NORMAL")  # WAL + NORMAL: durable across process crashes (kill -9)
            cur.execute("PRAGMA foreign_keys=ON")
            cur.execute("PRAGMA busy_timeout=30000")
            cur.close()

        @event.listens_for(engine, "begin")
        def _begin(conn):
            # Readers (engine option read_only) take no lock: in WAL mode they never block the writer.
            conn.exec_driver_sql("BEGIN" if conn.get_execution_options().get("read_only") else "BEGIN IMMEDIATE")

        return engine
    return create_engine(postgres_url(url), pool_pre_ping=True, pool_size=10, max_overflow=20)


def make_sessionmaker(engine: Engine, read_only: bool = False) -> sessionmaker:
    """Sessions for writing, or with ``read_only`` for reading (no write lock taken on SQLite)."""
    bind = engine.execution_options(read_only=True) if read_only else engine
    return sessionmaker(bind, expire_on_commit=False)


def upgrade(engine: Engine, revision: str = "head") -> None:
    """Run the packaged alembic migrations up to ``revision`` (idempotent; serialised across workers)."""
    from alembic import command
    from alembic.config import Config

    cfg = Config()
    cfg.set_main_option("script_location", str(MIGRATIONS_DIR))
    with engine.begin() as conn:
        if conn.dialect.name == "postgresql":
            # Several workers may start together; one upgrades, the others wait and then find it at head.
            conn.execute(text("SELECT pg_advisory_xact_lock(74726)"))
        cfg.attributes["connection"] = conn
        command.upgrade(cfg, revision)


def current_revision(engine: Engine) -> str | None:
    """The database's alembic revision, or None before the first migration."""
    from alembic.runtime.migration import MigrationContext

    with engine.connect() as conn:
        return MigrationContext.configure(conn).get_current_revision()


def head_revision() -> str:
    """The newest revision shipped in the package."""
    from alembic.config import Config
    from alembic.script import ScriptDirectory

    cfg = Config()
    cfg.set_main_option("script_location", str(MIGRATIONS_DIR))
    return ScriptDirectory.from_config(cfg).get_current_head()


def prune_idempotency_keys(engine: Engine, older_than_days: float) -> int:
    """Delete stored Idempotency-Keys older than ``older_than_days``; a retry after that is treated as new."""
    if older_than_days < 0:
        raise ValueError(f"older_than_days must be >= 0, got {older_than_days}")
    from sqlalchemy import delete

    cutoff = utcnow() - dt.timedelta(days=older_than_days)
    with engine.begin() as conn:
        return conn.execute(delete(IdempotencyKey).where(IdempotencyKey.created_at < cutoff)).rowcount


def _sqlite_path(url: str, action: str) -> str:
    if not url.startswith("sqlite:///"):
        raise SystemExit(f"db {action} handles SQLite files; for PostgreSQL use pg_dump / pg_restore "
                         "(deploy/RUNBOOK.md, 'Backup and restore')")
    return url[len("sqlite:///"):]


def _in_use_marker(path: str) -> Path:
    return Path(f"{path}.in-use")


def mark_sqlite_in_use(url: str):
    """Hold a shared advisory lock on ``<database>.in-use`` for as long as the returned file stays open (the life
    of a server process); ``restore_sqlite`` refuses while any process holds it. None for other databases."""
    import fcntl

    path = sqlite_file(url)
    if path is None:
        return None
    marker = open(_in_use_marker(str(path)), "a")   # noqa: SIM115 - kept open on purpose
    fcntl.flock(marker, fcntl.LOCK_SH)
    return marker


def backup_sqlite(url: str, target: str) -> None:
    """A consistent copy of a live SQLite database (SQLite's online backup; safe while the service writes)."""
    import sqlite3

    source = _sqlite_path(url, "backup")
    if not Path(source).is_file():
        raise SystemExit(f"no database at {source}; check JEPA_MONITOR_DATABASE_URL / --database-url")
    folder = Path(target).parent
    if not folder.is_dir():
        raise SystemExit(f"the folder {folder} of the backup {target} does not exist; create it (mkdir -p {folder}) "
                         "or give another path")
    if Path(target).is_dir():
        raise SystemExit(f"the backup {target} is a folder; give a file path, e.g. {Path(target) / 'monitor.db'}")
    try:
        with sqlite3.connect(source) as src, sqlite3.connect(target) as dst:
            src.backup(dst)
    except sqlite3.Error as exc:
        raise SystemExit(f"db backup to {target} failed: {exc}; check that the folder is writable and has room"
                         ) from None


def restore_sqlite(url: str, backup: str) -> None:
    """Replace the database with a backup; stop the service first. Refuses a file that is not a monitor backup."""
    import sqlite3

    target = _sqlite_path(url, "restore")
    if not Path(backup).is_file():
        raise SystemExit(f"backup {backup} not found")
    try:
        with sqlite3.connect(f"file:{backup}?mode=ro", uri=True) as src:
            tables = {row[0] for row in src.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
    except sqlite3.DatabaseError as exc:
        raise SystemExit(f"{backup} is not an SQLite database ({exc})") from None
    if not {"alembic_version", "episodes", "api_keys"} <= tables:
        raise SystemExit(f"{backup} is not a monitor database (no alembic_version / episodes / api_keys tables)")
    import fcntl

    with open(_in_use_marker(target), "a") as marker:
        try:
            fcntl.flock(marker, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise SystemExit(f"a monitor server is serving {target}: stop it first (deploy/RUNBOOK.md, 'Backup and "
                             "restore'); a restore under a live server would lose what it writes") from None
        with sqlite3.connect(backup) as src, sqlite3.connect(target) as dst:
            src.backup(dst)
