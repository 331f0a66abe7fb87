"""Fewer index writes per ingested record: every decision and realized latent was written into two indexes
that duplicate another (``ix_decisions_episode_id`` and ``ix_targets_episode_id``: the unique (episode_id, step)
constraints already index episode_id as their first column) and one that nothing reads
(``ix_decisions_episode_target``: the ingest path finds a target's decisions in memory). Dropping them makes a
batch commit write fewer pages (jepa-monitor bench, docs/monitor.md "Throughput").

Revision ID: 0003
Revises: 0002
"""
from alembic import op

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.drop_index("ix_decisions_episode_target", table_name="decisions")
    op.drop_index("ix_decisions_episode_id", table_name="decisions")
    op.drop_index("ix_targets_episode_id", table_name="targets")


def downgrade() -> None:
    op.create_index("ix_targets_episode_id", "targets", ["episode_id"])
    op.create_index("ix_decisions_episode_id", "decisions", ["episode_id"])
    op.create_index("ix_decisions_episode_target", "decisions", ["episode_id", "target_step"])
