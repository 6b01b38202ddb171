"""Schema version 5: ``iterations.terms_json``, the objective's named terms of each step (the victim's
loss, the total and each regulariser's value; NULL for the steps of a run without regularisers).

Revision ID: 0005
Revises: 0004
"""
import sqlalchemy as sa
from alembic import op

revision = "0005"
down_revision = "0004"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column("iterations", sa.Column("terms_json", sa.Text(), nullable=True))
