"""Alembic migrations of the run database (applied by :func:`undream.store.db.create_tables`).

A new database is made by ``Base.metadata.create_all`` and stamped at the
head revision; an existing one is upgraded in place, in the transaction that
opens it. Databases made before alembic (schema versions 1–3 in
``undream_schema``) are first brought to version 3 by the hand-written steps
in :mod:`undream.store.db`, stamped ``0003``, then upgraded from there.

A new revision: ``alembic -c undream/store/migrations/alembic.ini revision -m "what"``,
then write its ``upgrade`` with alembic's operations, bump ``SCHEMA_VERSION`` in
:mod:`undream.store.models` and declare the same change on the models.
"""
