"""Per-minute temperature rollups for fast long histories.

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-22 15:20:00
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0003"
down_revision: str | None = "0002"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Apply this revision."""
    op.create_table(
        "temperature_rollups",
        sa.Column("campaign_id", sa.Integer(), nullable=False),
        sa.Column("channel_id", sa.Integer(), nullable=False),
        sa.Column("minute", sa.Integer(), nullable=False),
        sa.Column("n", sa.Integer(), nullable=False),
        sa.Column("n_values", sa.Integer(), nullable=False),
        sa.Column("vmin", sa.Double(), nullable=True),
        sa.Column("vsum", sa.Double(), nullable=True),
        sa.Column("vmax", sa.Double(), nullable=True),
        sa.PrimaryKeyConstraint("campaign_id", "channel_id", "minute", name=op.f("pk_temperature_rollups")),
        sqlite_with_rowid=False,
    )
    with op.batch_alter_table("campaigns", schema=None) as batch_op:
        batch_op.add_column(
            sa.Column("rollups_complete", sa.Boolean(), server_default=sa.text("false"), nullable=False)
        )


def downgrade() -> None:
    """Revert this revision."""
    with op.batch_alter_table("campaigns", schema=None) as batch_op:
        batch_op.drop_column("rollups_complete")
    op.drop_table("temperature_rollups")
