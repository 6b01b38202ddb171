"""A run's states and the size of a page of runs, named apart from the store so that a command can
offer them (``--state``, ``--limit``) without loading SQLAlchemy; :mod:`undream.store` checks its
columns and pages against the same values."""
from __future__ import annotations

RUN_STATUSES = ("queued", "running", "evaluating", "done", "failed", "cancelled")
ACTIVE_STATUSES = ("queued", "running", "evaluating")  # a run in one of these has work left
MAX_PAGE = 1_000  # runs in one page of a list at most (`undream status --limit`, the API's `limit`)
