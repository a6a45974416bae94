"""Bundle v2: the full commanded pose and the instrument setup of every error reading.

Revision ID: 0005
Revises: 0004
Create Date: 2026-11-24 22:40:00
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0005"
down_revision: str | None = "0004"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

POSE = ("x", "y", "z", "a", "b")


def upgrade() -> None:
    """Add nullable pose columns and the setup id to error_samples (v1 readings keep NULL)."""
    with op.batch_alter_table("error_samples") as batch:
        for name in POSE:
            batch.add_column(sa.Column(name, sa.Double(), nullable=True))
        batch.add_column(sa.Column("setup", sa.String(length=64), nullable=True))


def downgrade() -> None:
    """Drop the pose and setup columns."""
    with op.batch_alter_table("error_samples") as batch:
        batch.drop_column("setup")
        for name in reversed(POSE):
            batch.drop_column(name)
