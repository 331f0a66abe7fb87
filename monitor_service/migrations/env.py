"""Alembic environment: always run online on the connection handed over by monitor_service.db.upgrade."""
from alembic import context

from monitor_service.db import Base

connection = context.config.attributes.get("connection")
if connection is None:
    raise RuntimeError("run migrations with `jepa-monitor db upgrade` (monitor_service.db.upgrade), not bare alembic")
context.configure(connection=connection, target_metadata=Base.metadata, render_as_batch=True)
with context.begin_transaction():
    context.run_migrations()
