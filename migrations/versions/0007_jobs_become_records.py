"""The ``jobs`` table becomes the record of each job, no longer a queue.

Revision ID: 0007
Revises: 0006
Create Date: 2026-12-02 10:30:00

Jobs are queued by procrastinate on PostgreSQL (revision 0006) and run in-process on SQLite, so the
hand-written queue goes: no claims, no heartbeats (procrastinate's workers beat in their own table),
no claim index. The table stays as the history the API reports, which a queue does not keep: what
was asked (params, machine, campaign), what came out (the fit or diagnosis report, or a one-line
error), attempts and times. ``queue_job_id`` links a record to its procrastinate job
(procrastinate_jobs.id) so that the API can report the queue's own state; it is NULL on SQLite.
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0007"
down_revision: str | None = "0006"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Drop the claim index and the heartbeat; add the queue job id and the per-machine index."""
    with op.batch_alter_table("jobs", schema=None) as batch_op:
        batch_op.drop_index("ix_jobs_state_id")
        batch_op.drop_column("heartbeat_at")
        batch_op.add_column(sa.Column("queue_job_id", sa.BigInteger(), nullable=True))
        batch_op.create_index("ix_jobs_machine_id_id", ["machine_id", "id"], unique=False)


def downgrade() -> None:
    """Put the claim index and the heartbeat column back (records keep their rows)."""
    with op.batch_alter_table("jobs", schema=None) as batch_op:
        batch_op.drop_index("ix_jobs_machine_id_id")
        batch_op.drop_column("queue_job_id")
        batch_op.add_column(sa.Column("heartbeat_at", sa.DateTime(timezone=True), nullable=True))
        batch_op.create_index("ix_jobs_state_id", ["state", "id"], unique=False)
