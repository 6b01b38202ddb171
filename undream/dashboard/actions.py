"""The dashboard's only writes: cancel and resume a run, each behind the settings' ``dashboard_token``.

The token comes in the ``X-Undream-Token`` header (API) or the ``token``
form field (the run page's buttons); it is compared in constant time. No
token configured, none given or a wrong one: :class:`Forbidden`, and nothing
is read or written. Cancel needs only the store; resume also sends the run's
work to the broker (:func:`scheduler.stages.resume`), so an unreachable
broker is :class:`Unavailable`.
"""
from __future__ import annotations

import hmac
from typing import TYPE_CHECKING, Any

from undream.dashboard.errors import Conflict, Forbidden, NotFound, Unavailable
from undream.errors import UndreamError
from workers.dispatch import CeleryDispatch

if TYPE_CHECKING:
    from undream.settings import Settings
    from undream.store import Store

ACTIONS = ("cancel", "resume")
TOKEN_HEADER = "X-Undream-Token"


def check_token(settings: "Settings", given: str | None) -> None:
    """Return when ``given`` is the dashboard token, else :class:`Forbidden` (never echoing either)."""
    expected = settings.dashboard_token
    if expected is None:
        raise Forbidden("actions are disabled: set dashboard_token (UNDREAM_DASHBOARD_TOKEN) to allow "
                        "cancel and resume")
    if not given:
        raise Forbidden(f"this action needs the dashboard token ({TOKEN_HEADER} header or token field)")
    if not hmac.compare_digest(given.encode("utf-8"), expected.encode("utf-8")):
        raise Forbidden("wrong dashboard token")


def _cancel(store: "Store", run_id: str) -> dict[str, Any]:
    from scheduler.stages import cancel

    if not cancel(store, run_id):
        status = store.get_run(run_id).status
        raise Conflict(f"run {run_id} is {status}; nothing to cancel")
    return {"run_id": run_id, "action": "cancel", "status": store.get_run(run_id).status}


def _resume(settings: "Settings", store: "Store", run_id: str) -> dict[str, Any]:
    from scheduler.stages import resume
    from workers.app import BrokerError, check_reachable, create_celery_app

    if store.get_run(run_id).status == "done":
        raise Conflict(f"run {run_id} is done; nothing to resume")
    app = create_celery_app(settings)
    try:
        check_reachable(app, settings)
        phase = resume(store, run_id, CeleryDispatch(app))
    except BrokerError as err:
        raise Unavailable(" ".join(str(err).split())) from None
    except UndreamError:
        raise
    except Exception as exc:  # kombu's OperationalError and the transport's own errors while sending
        raise Unavailable(f"run {run_id}: resume recorded but not sent to the broker "
                          f"({' '.join(str(exc).split())}); resume it again") from None
    finally:
        app.close()
    return {"run_id": run_id, "action": "resume", "phase": phase, "status": store.get_run(run_id).status}


def act(settings: "Settings", store: "Store", run_id: str, action: str, token: str | None) -> dict[str, Any]:
    """Check the token, then cancel or resume ``run_id``; returns what happened (plain data)."""
    if action not in ACTIONS:
        raise NotFound(f"action {action!r}: unknown; valid actions are {', '.join(ACTIONS)}")
    check_token(settings, token)
    store.get_run(run_id)
    return _cancel(store, run_id) if action == "cancel" else _resume(settings, store, run_id)
