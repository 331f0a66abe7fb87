"""Initial schema: keys, tasks, episodes, decisions, targets, calibrations, alerts, webhooks, idempotency.

Revision ID: 0001
Revises:
"""
import sqlalchemy as sa
from alembic import op

revision = "0001"
down_revision = None
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "api_keys",
        sa.Column("id", sa.Integer, primary_key=True),
        sa.Column("name", sa.String(128), nullable=False, unique=True),
        sa.Column("key_hash", sa.String(64), nullable=False, unique=True),
        sa.Column("role", sa.String(16), nullable=False),
        sa.Column("robot", sa.String(128), nullable=True),
        sa.Column("created_at", sa.DateTime, nullable=False),
        sa.Column("revoked_at", sa.DateTime, nullable=True),
    )
    op.create_table(
        "tasks",
        sa.Column("name", sa.String(128), primary_key=True),
        sa.Column("latent_dim", sa.Integer, nullable=True),
        sa.Column("description", sa.String(512), nullable=False),
        sa.Column("created_at", sa.DateTime, nullable=False),
    )
    op.create_table(
        "episodes",
        sa.Column("id", sa.String(128), primary_key=True),
        sa.Column("task", sa.String(128), sa.ForeignKey("tasks.name"), nullable=False, index=True),
        sa.Column("robot", sa.String(128), nullable=False, index=True),
        sa.Column("checkpoint", sa.String(256), nullable=True),
        sa.Column("group_name", sa.String(128), nullable=True),
        sa.Column("held_out", sa.Boolean, nullable=False),
        sa.Column("success", sa.Boolean, nullable=True),
        sa.Column("early_score", sa.Float, nullable=True),
        sa.Column("running_score", sa.Float, nullable=True),
        sa.Column("n_decisions", sa.Integer, nullable=False),
        sa.Column("n_scored", sa.Integer, nullable=False),
        sa.Column("last_evaluated_step", sa.Integer, nullable=False),
        sa.Column("over_count", sa.Integer, nullable=False),
        sa.Column("under_count", sa.Integer, nullable=False),
        sa.Column("open_alert_id", sa.Integer, nullable=True),
        sa.Column("alert_note", sa.String(512), nullable=False),
        sa.Column("started_at", sa.DateTime, nullable=False),
        sa.Column("updated_at", sa.DateTime, nullable=False, index=True),
        sa.Column("ended_at", sa.DateTime, nullable=True),
    )
    op.create_table(
        "decisions",
        sa.Column("id", sa.Integer, primary_key=True),
        sa.Column("episode_id", sa.String(128), sa.ForeignKey("episodes.id"), nullable=False, index=True),
        sa.Column("step", sa.Integer, nullable=False),
        sa.Column("horizon", sa.Integer, nullable=False),
        sa.Column("target_step", sa.Integer, nullable=False),
        sa.Column("z_hat", sa.LargeBinary, nullable=False),
        sa.Column("nmse", sa.Float, nullable=True),
        sa.Column("created_at", sa.DateTime, nullable=False),
        sa.UniqueConstraint("episode_id", "step", name="uq_decision_episode_step"),
    )
    op.create_index("ix_decisions_episode_target", "decisions", ["episode_id", "target_step"])
    op.create_table(
        "targets",
        sa.Column("id", sa.Integer, primary_key=True),
        sa.Column("episode_id", sa.String(128), sa.ForeignKey("episodes.id"), nullable=False, index=True),
        sa.Column("step", sa.Integer, nullable=False),
        sa.Column("z", sa.LargeBinary, nullable=False),
        sa.Column("created_at", sa.DateTime, nullable=False),
        sa.UniqueConstraint("episode_id", "step", name="uq_target_episode_step"),
    )
    op.create_table(
        "calibrations",
        sa.Column("id", sa.Integer, primary_key=True),
        sa.Column("task", sa.String(128), sa.ForeignKey("tasks.name"), nullable=False, index=True),
        sa.Column("checkpoint", sa.String(256), nullable=True),
        sa.Column("active", sa.Boolean, nullable=False),
        sa.Column("threshold_rule", sa.String(16), nullable=False),
        sa.Column("threshold", sa.Float, nullable=True),
        sa.Column("auroc", sa.Float, nullable=False),
        sa.Column("result", sa.JSON, nullable=False),
        sa.Column("created_at", sa.DateTime, nullable=False),
    )
    op.create_table(
        "alerts",
        sa.Column("id", sa.Integer, primary_key=True),
        sa.Column("episode_id", sa.String(128), sa.ForeignKey("episodes.id"), nullable=False, index=True),
        sa.Column("task", sa.String(128), nullable=False, index=True),
        sa.Column("robot", sa.String(128), nullable=False),
        sa.Column("step", sa.Integer, nullable=False),
        sa.Column("score", sa.Float, nullable=False),
        sa.Column("threshold", sa.Float, nullable=False),
        sa.Column("calibration_id", sa.Integer, nullable=False),
        sa.Column("state", sa.String(16), nullable=False, index=True),
        sa.Column("acknowledged_by", sa.String(128), nullable=True),
        sa.Column("acknowledged_at", sa.DateTime, nullable=True),
        sa.Column("note", sa.String(512), nullable=False),
        sa.Column("raised_at", sa.DateTime, nullable=False),
        sa.Column("cleared_at", sa.DateTime, nullable=True),
    )
    op.create_table(
        "webhook_deliveries",
        sa.Column("id", sa.Integer, primary_key=True),
        sa.Column("alert_id", sa.Integer, sa.ForeignKey("alerts.id"), nullable=False, index=True),
        sa.Column("url", sa.String(1024), nullable=False),
        sa.Column("status", sa.String(16), nullable=False, index=True),
        sa.Column("attempts", sa.Integer, nullable=False),
        sa.Column("next_attempt_at", sa.DateTime, nullable=False),
        sa.Column("claimed_until", sa.DateTime, nullable=True),
        sa.Column("last_error", sa.String(1024), nullable=False),
    )
    op.create_table(
        "idempotency_keys",
        sa.Column("id", sa.Integer, primary_key=True),
        sa.Column("api_key_id", sa.Integer, nullable=False),
        sa.Column("key", sa.String(128), nullable=False),
        sa.Column("request_hash", sa.String(64), nullable=False),
        sa.Column("status_code", sa.Integer, nullable=False),
        sa.Column("response", sa.JSON, nullable=False),
        sa.Column("created_at", sa.DateTime, nullable=False),
        sa.UniqueConstraint("api_key_id", "key", name="uq_idempotency_owner_key"),
    )


def downgrade() -> None:
    for table in (
        "idempotency_keys",
        "webhook_deliveries",
        "alerts",
        "calibrations",
        "targets",
        "decisions",
        "episodes",
        "tasks",
        "api_keys",
    ):
        op.drop_table(table)
