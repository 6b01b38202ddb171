"""Secrets out of everything shown or written: passwords in URLs, tokens in query strings.

A database or broker URL (``postgresql://user:PASSWORD@host/db``,
``redis://:PASSWORD@host:6379/0``, ``s3://KEY:SECRET@bucket``) keeps its
password in the settings and the run store, where the farm needs it. Every
edge that shows or writes one — a run's ``metadata.json``, the report, the
dashboard's pages and JSON API, error lines, log lines — passes it through
:func:`redact` first, which replaces the secret with ``***`` and keeps the
rest (scheme, user, host, port, path) so the reader still sees where it points.
"""
from __future__ import annotations

import logging
import re
from typing import Any

MASK = "***"

# userinfo's password: scheme://user:PASSWORD@ (user may be empty)
_USERINFO = re.compile(r"(?P<head>[A-Za-z][A-Za-z0-9+.\-]*://[^/@\s:]*:)(?P<secret>[^@\s/]*)@")
# secrets in a query string or key=value text: password=…, token=…, secret=…, key=…
_QUERY = re.compile(r"(?P<head>[?&;\s]?(?:password|passwd|pwd|token|secret|api_key|apikey|access_key|"
                    r"secret_key|aws_secret_access_key|sslpassword)=)(?P<secret>[^&\s'\"]+)", re.IGNORECASE)


def redact_text(text: str) -> str:
    """``text`` with every URL password and query-string secret replaced by ``***``."""
    text = _USERINFO.sub(lambda m: f"{m['head']}{MASK}@", text)
    return _QUERY.sub(lambda m: f"{m['head']}{MASK}", text)


def redact(value: Any) -> Any:
    """``value`` (a string, or mappings and lists of them, e.g. a run config) with every secret in
    every string redacted (:func:`redact_text`); a new object, the argument is not changed."""
    if isinstance(value, str):
        return redact_text(value)
    if isinstance(value, dict):
        return {redact(k): redact(v) for k, v in value.items()}
    if isinstance(value, list):
        return [redact(v) for v in value]
    if isinstance(value, tuple):
        return tuple(redact(v) for v in value)
    return value


def install_log_redaction() -> None:
    """Redact every log record of this process (and of the processes it forks) as it is made:
    a password that reaches a log line through an error message or a URL is ``***`` in the log."""
    make = logging.getLogRecordFactory()
    if getattr(make, "undream_redacts", False):
        return

    def factory(*args: Any, **kwargs: Any) -> logging.LogRecord:
        record = make(*args, **kwargs)
        try:
            message = record.getMessage()
        except Exception:  # a malformed record: logging reports it as it would have
            return record
        if message != (redacted := redact_text(message)):
            record.msg, record.args = redacted, ()
        return record

    factory.undream_redacts = True  # type: ignore[attr-defined]
    logging.setLogRecordFactory(factory)
