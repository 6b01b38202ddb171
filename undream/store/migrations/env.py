"""Alembic's environment: runs on the connection :func:`undream.store.db.create_tables` hands over."""
from __future__ import annotations

from alembic import context

from undream.store.models import Base

connection = context.config.attributes.get("connection")
if connection is None:
    raise RuntimeError("undream applies its migrations itself when it opens a database "
                       "(undream.store.db.create_tables); there is no URL to run them against here")
context.configure(connection=connection, target_metadata=Base.metadata, render_as_batch=True)
with context.begin_transaction():
    context.run_migrations()
