"""Per-length thresholds, gaps in the decision stream, the alert life cycle and named per-decision scores.

- episodes: the threshold the latest rule value was judged against, the calibrated length and whether the
  episode ran beyond it, decision indices skipped (count and the first steps), decisions that arrived after a
  later one, how often the published early score changed, and the state of per-signal rules;
- decisions: named scores beside (or instead of) the latents: z_hat, horizon and target_step become optional;
- alerts: resolved by the episode's outcome (when, and as a true or a false alert), whether raised beyond the
  calibrated length, which signals raised it; an acknowledged alert that is still running is 'acknowledged';
- tasks: the named signals robots may send.

Revision ID: 0004
Revises: 0003
"""
import sqlalchemy as sa
from alembic import op

revision = "0004"
down_revision = "0003"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("episodes") as batch:
        batch.add_column(sa.Column("risk_threshold", sa.Float, nullable=True))
        batch.add_column(sa.Column("calibrated_decisions", sa.Integer, nullable=True))
        batch.add_column(sa.Column("beyond_calibration", sa.Boolean, nullable=False, server_default=sa.false()))
        batch.add_column(sa.Column("gaps", sa.Integer, nullable=False, server_default="0"))
        batch.add_column(sa.Column("gap_steps", sa.JSON, nullable=True))
        batch.add_column(sa.Column("late_decisions", sa.Integer, nullable=False, server_default="0"))
        batch.add_column(sa.Column("early_revisions", sa.Integer, nullable=False, server_default="0"))
        batch.add_column(sa.Column("signal_state", sa.JSON, nullable=True))
    with op.batch_alter_table("decisions") as batch:
        batch.add_column(sa.Column("scores", sa.JSON, nullable=True))
        batch.alter_column("z_hat", existing_type=sa.LargeBinary, nullable=True)
        batch.alter_column("horizon", existing_type=sa.Integer, nullable=True)
        batch.alter_column("target_step", existing_type=sa.Integer, nullable=True)
    with op.batch_alter_table("alerts") as batch:
        batch.add_column(sa.Column("resolved_at", sa.DateTime, nullable=True))
        batch.add_column(sa.Column("resolution", sa.String(16), nullable=True))
        batch.add_column(sa.Column("beyond_calibration", sa.Boolean, nullable=False, server_default=sa.false()))
        batch.add_column(sa.Column("signals", sa.String(512), nullable=False, server_default="nmse"))
    with op.batch_alter_table("tasks") as batch:
        batch.add_column(sa.Column("signals", sa.JSON, nullable=True))
    op.execute("UPDATE alerts SET state = 'acknowledged' WHERE state = 'open' AND acknowledged_at IS NOT NULL")
    op.execute(
        "UPDATE alerts SET state = 'resolved', "
        "resolved_at = (SELECT e.ended_at FROM episodes e WHERE e.id = alerts.episode_id), "
        "resolution = (SELECT CASE WHEN e.success THEN 'success' ELSE 'failure' END FROM episodes e "
        "WHERE e.id = alerts.episode_id) "
        "WHERE state IN ('open', 'acknowledged') AND episode_id IN "
        "(SELECT id FROM episodes WHERE success IS NOT NULL)")
    op.execute("UPDATE episodes SET open_alert_id = NULL WHERE success IS NOT NULL")


def downgrade() -> None:
    op.execute("UPDATE alerts SET state = 'open' WHERE state IN ('acknowledged', 'resolved')")
    with op.batch_alter_table("tasks") as batch:
        batch.drop_column("signals")
    with op.batch_alter_table("alerts") as batch:
        batch.drop_column("signals")
        batch.drop_column("beyond_calibration")
        batch.drop_column("resolution")
        batch.drop_column("resolved_at")
    with op.batch_alter_table("decisions") as batch:
        batch.alter_column("target_step", existing_type=sa.Integer, nullable=False)
        batch.alter_column("horizon", existing_type=sa.Integer, nullable=False)
        batch.alter_column("z_hat", existing_type=sa.LargeBinary, nullable=False)
        batch.drop_column("scores")
    with op.batch_alter_table("episodes") as batch:
        for name in ("signal_state", "early_revisions", "late_decisions", "gap_steps", "gaps", "beyond_calibration",
                     "calibrated_decisions", "risk_threshold"):
            batch.drop_column(name)
