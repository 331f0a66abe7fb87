"""Persistence control, episode length and risk: decisions may carry the current latent z_t (the persistence
baseline z_hat = z_t is scored against the same realized target), outcomes may carry the episode's length, and
an episode keeps the latest value of its calibrated alert rule's statistic and a version counter.

Revision ID: 0002
Revises: 0001
"""
import sqlalchemy as sa
from alembic import op

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("decisions") as batch:
        batch.add_column(sa.Column("z_now", sa.LargeBinary, nullable=True))
        batch.add_column(sa.Column("nmse_persistence", sa.Float, nullable=True))
    with op.batch_alter_table("episodes") as batch:
        batch.add_column(sa.Column("length", sa.Integer, nullable=True))
        batch.add_column(sa.Column("risk_score", sa.Float, nullable=True))
        # optimistic concurrency of the in-memory episode state of each server process (ingest.py)
        batch.add_column(sa.Column("version", sa.Integer, nullable=False, server_default="0"))


def downgrade() -> None:
    with op.batch_alter_table("episodes") as batch:
        batch.drop_column("version")
        batch.drop_column("risk_score")
        batch.drop_column("length")
    with op.batch_alter_table("decisions") as batch:
        batch.drop_column("nmse_persistence")
        batch.drop_column("z_now")
