"""Index error samples by sweep for the interpolating drift query.

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-22 14:55:00
"""

from __future__ import annotations

from collections.abc import Sequence

from alembic import op

revision: str = "0002"
down_revision: str | None = "0001"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Apply this revision."""
    with op.batch_alter_table("error_samples", schema=None) as batch_op:
        batch_op.create_index(
            "ix_error_samples_sweep", ["campaign_id", "axis", "term", "direction", "sweep", "position"], unique=False
        )


def downgrade() -> None:
    """Revert this revision."""
    with op.batch_alter_table("error_samples", schema=None) as batch_op:
        batch_op.drop_index("ix_error_samples_sweep")
