"""The daemon's heartbeat: acquisition_progress.heartbeat_at (issue 24: stale campaigns are shown as such).

Revision ID: 0009
Revises: 0008
Create Date: 2026-11-25 16:10:00

A campaign the daemon was running when it was killed stays ``running`` in the store; its heartbeat
(written every few seconds by the running daemon, waiting or not) tells status, /live and --watch
that nobody runs it any more. Existing rows get NULL: their last commit (``updated_at``) stands in.
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0009"
down_revision: str | None = "0008"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Apply this revision."""
    with op.batch_alter_table("acquisition_progress", schema=None) as batch_op:
        batch_op.add_column(sa.Column("heartbeat_at", sa.DateTime(timezone=True), nullable=True))


def downgrade() -> None:
    """Revert this revision."""
    with op.batch_alter_table("acquisition_progress", schema=None) as batch_op:
        batch_op.drop_column("heartbeat_at")
