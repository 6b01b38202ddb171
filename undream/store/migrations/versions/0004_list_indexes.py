"""Schema version 4: the indexes that let the control plane read a page of runs newest first
(all runs, by status, or by sweep) without scanning the table.

Revision ID: 0004
Revises: 0003
"""
from alembic import op

revision = "0004"
down_revision = "0003"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_index("ix_runs_created_id", "runs", ["created", "id"])
    op.create_index("ix_runs_status_created_id", "runs", ["status", "created", "id"])
    op.create_index("ix_runs_sweep_created_id", "runs", ["sweep_id", "created", "id"])
