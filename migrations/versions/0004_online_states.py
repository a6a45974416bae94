"""On-line (RLS) state per machine; probe measurements keep their readings.

Revision ID: 0004
Revises: 0003
Create Date: 2026-11-22 16:10:00
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects import postgresql

revision: str = "0004"
down_revision: str | None = "0003"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def _json() -> sa.types.TypeEngine:
    return sa.JSON().with_variant(postgresql.JSONB(astext_type=sa.Text()), "postgresql")


def upgrade() -> None:
    """Apply this revision."""
    op.create_table(
        "online_states",
        sa.Column("machine_id", sa.String(length=64), nullable=False),
        sa.Column("model_version_id", sa.Integer(), nullable=True),
        sa.Column("model_version", sa.Integer(), nullable=False),
        sa.Column("lam", sa.Double(), nullable=False),
        sa.Column("n_updates", sa.Integer(), nullable=False),
        sa.Column("theta", _json(), nullable=False),
        sa.Column("p", _json(), nullable=False),
        sa.Column("updated_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("version", sa.Integer(), nullable=False),
        sa.ForeignKeyConstraint(
            ["machine_id"], ["machines.id"], name=op.f("fk_online_states_machine_id_machines"), ondelete="CASCADE"
        ),
        sa.ForeignKeyConstraint(
            ["model_version_id"],
            ["model_versions.id"],
            name=op.f("fk_online_states_model_version_id_model_versions"),
            ondelete="SET NULL",
        ),
        sa.PrimaryKeyConstraint("machine_id", name=op.f("pk_online_states")),
    )
    with op.batch_alter_table("probe_measurements", schema=None) as batch_op:
        batch_op.add_column(sa.Column("temperatures", _json(), nullable=True))


def downgrade() -> None:
    """Revert this revision."""
    with op.batch_alter_table("probe_measurements", schema=None) as batch_op:
        batch_op.drop_column("temperatures")
    op.drop_table("online_states")
