"""Schema version 3, the last one made without alembic: runs (with their leases), sweeps,
iterations, frame jobs. Databases of versions 1–3 are brought here by the hand-written steps in
undream.store.db and stamped with this revision; it creates nothing itself.

Revision ID: 0003
Revises:
"""
revision = "0003"
down_revision = None
branch_labels = None
depends_on = None


def upgrade() -> None:
    pass
