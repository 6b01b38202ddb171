"""The dashboard's failures, each mapped to one HTTP status at the edge (:mod:`undream.dashboard.app`).

The store raises :class:`~undream.errors.StoreError` for a missing run as
for an unreachable database; :func:`from_store_error` tells them apart by
what caused it: the store raises a database or file-system failure ``from``
the SQLAlchemy or OS error, and a missing row or blob with no cause.
"""
from __future__ import annotations

from undream.errors import StoreError, UndreamError


class DashboardError(UndreamError):
    """A request the dashboard cannot answer; ``status`` is its HTTP status code."""

    status = 500


class BadRequest(DashboardError):
    """A query parameter is not one of its valid values."""

    status = 400


class Forbidden(DashboardError):
    """An action without the dashboard token, with a wrong one, or with actions disabled."""

    status = 403


class NotFound(DashboardError):
    """No run, sweep, iteration, frame or artifact by that id."""

    status = 404


class Conflict(DashboardError):
    """An action that does not apply to the run as it is (cancel a finished run)."""

    status = 409


class Unavailable(DashboardError):
    """The database, the blob store or the broker cannot be reached."""

    status = 503


def from_store_error(err: StoreError) -> DashboardError:
    """:class:`Unavailable` for a StoreError caused by the database or the disk, else :class:`NotFound`."""
    message = " ".join(str(err).split())
    if err.__cause__ is not None:
        return Unavailable(message)
    return NotFound(message)
