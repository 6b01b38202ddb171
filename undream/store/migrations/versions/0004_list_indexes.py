"""Schema version 4: the indexes that let the control plane read a page of runs newest first
(all runs, by status, or by sweep), the runs a process owns, and a run's jobs at its current
iteration, without scanning a table; and the ``blobs`` table of the ``database`` blob backend.

Revision ID: 0004
Revises: 0003
"""
import sqlalchemy as sa
from alembic import op

from undream.store.models import Blob

revision = "0004"
down_revision = "0003"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_index("ix_runs_created_id", "runs", ["created", "id"])
    op.create_index("ix_runs_status_created_id", "runs", ["status", "created", "id"])
    op.create_index("ix_runs_sweep_created_id", "runs", ["sweep_id", "created", "id"])
    op.create_index("ix_runs_owner", "runs", ["owner"])
    op.create_index("ix_frame_jobs_run_k_status", "frame_jobs", ["run_id", "k", "status"])
    failed = sa.text("error IS NOT NULL")
    op.create_index("ix_frame_jobs_failed", "frame_jobs", ["run_id"], sqlite_where=failed, postgresql_where=failed)
    Blob.__table__.create(op.get_bind(), checkfirst=True)  # as declared (this revision is the model's first)
