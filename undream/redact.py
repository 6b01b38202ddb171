"""Secrets out of everything shown or written: passwords in URLs, tokens in query strings, request signatures.

A database or broker URL (``postgresql://user:PASSWORD@host/db``,
``redis://:PASSWORD@host:6379/0``, ``s3://KEY:SECRET@bucket``) keeps its
password in the settings and the run store, where the farm needs it. Every
edge that shows or writes one — a run's ``metadata.json``, the report, the
dashboard's pages and JSON API, error lines, log lines — passes it through
:func:`redact` first, which replaces the secret with ``***`` and keeps the
rest (scheme, user, host, port, path) so the reader still sees where it points.

A password may hold any character. URL parsers disagree on where it ends:
SQLAlchemy reads up to the first ``@`` (``postgresql://u:ab/cd@host/db`` has the
password ``ab/cd``), urllib, redis and kombu up to the last ``@`` before the
first ``/`` (``redis://:p@ss@host/0`` has ``p@ss``). The secret masked here
reaches at least as far as every one of them reads: to the last ``@`` of the
URL. In free text (:func:`redact_text`: logs, pages, error lines) the URL ends
at whitespace, an unescaped quote, ``<`` or ``>`` (``\\"`` inside a JSON string
does not end it); a value that is one string of a config (:func:`redact`) ends
only at a line break.

S3 request signing (botocore at DEBUG) is masked too: ``Authorization``
headers, ``X-Amz-Security-Token``, ``X-Amz-Credential``/``Credential=`` (the
access key id), ``Signature``/``X-Amz-Signature`` and ``AWSAccessKeyId``.
"""
from __future__ import annotations

import logging
import re
from typing import Any, Iterable

MASK = "***"
_MIN_LITERAL = 6  # shorter literal secrets are not masked in logs (they would mask ordinary words)


def _userinfo(stop: str, markup: str = "") -> re.Pattern[str]:
    """``scheme://user:PASSWORD@`` in a URL that ends at any character of ``stop`` or ``markup``
    (regex class bodies). The password runs to the last ``@`` of the URL, else (a ``markup``
    character before it: a ``<`` of a password in a log line) to the last ``@`` before its first
    ``/``, ``?`` or ``#``. The user may hold ``@`` (``user@server``); a backslash-escaped quote
    belongs to the URL (``\\"`` in a JSON string)."""
    esc = r"\\[\"']"
    whole, netloc = rf"(?:{esc}|[^{stop}{markup}])*@", rf"(?:{esc}|[^/?#{stop}])*@"
    return re.compile(rf"(?P<head>[A-Za-z][A-Za-z0-9+.\-]*://[^:/{stop}{markup}]*:)(?P<secret>{whole}|{netloc})")


_TEXT_URL = _userinfo(r"\s'\"", "<>")  # free text: a URL ends at whitespace, a quote, < or >
_VALUE_URL = _userinfo(r"\r\n")  # one string value: it ends at a line break
# secrets in a query string or key=value text: password=…, token=…, secret=…, key=…
_QUERY = re.compile(r"(?P<head>[?&;\s]?(?:password|passwd|pwd|token|secret|api_key|apikey|access_key|"
                    r"secret_key|aws_secret_access_key|sslpassword)=)(?P<secret>[^&\s'\"]+)", re.IGNORECASE)
# an HTTP authorization header's value, in a header line or a repr of headers ('Authorization': b'…')
_AUTH_HEADER = re.compile(r"(?P<head>\b(?:proxy-)?authorization['\"]?\s*[:=]\s*(?:b?['\"])?)(?P<secret>[^'\"\r\n]+)",
                          re.IGNORECASE)
# S3 request signing as botocore logs it: headers, presigned-URL parameters, 'Signature:\n<hex>'
_SIGNING = re.compile(r"(?P<head>\b(?:x-amz-security-token|x-amz-credential|x-amz-signature|awsaccesskeyid|"
                      r"signature|credential)['\"]?\s*[:=]\s*(?:b?['\"])?)(?P<secret>[^\s'\",&;]+)", re.IGNORECASE)
_SECRETS = (_QUERY, _AUTH_HEADER, _SIGNING)


def _mask(text: str, url: re.Pattern[str]) -> str:
    text = url.sub(lambda m: f"{m['head']}{MASK}@", text)
    for pattern in _SECRETS:
        text = pattern.sub(lambda m: f"{m['head']}{MASK}", text)
    return text


def redact_text(text: str) -> str:
    """``text`` (free text: a log line, a page, an error) with every URL password, query-string
    secret and request signature replaced by ``***`` (see the module docstring)."""
    return _mask(text, _TEXT_URL)


def redact(value: Any) -> Any:
    """``value`` (a string, or mappings and lists of them, e.g. a run config) with every secret in
    every string redacted, each string read as one value (a password may hold quotes or spaces);
    a new object, the argument is not changed."""
    if isinstance(value, str):
        return _mask(value, _VALUE_URL)
    if isinstance(value, dict):
        return {redact(k): redact(v) for k, v in value.items()}
    if isinstance(value, list):
        return [redact(v) for v in value]
    if isinstance(value, tuple):
        return tuple(redact(v) for v in value)
    return value


_LOG_SECRETS: set[str] = set()  # literal values masked in every log record (the S3 keys of a worker)


def _redact_log(text: str) -> str:
    """``text`` redacted (:func:`redact_text`), with every registered literal secret masked too."""
    text = redact_text(text)
    for secret in sorted(_LOG_SECRETS, key=len, reverse=True):
        text = text.replace(secret, MASK)
    return text


def _redact_record(record: logging.LogRecord) -> None:
    """Redact ``record``'s message and its traceback text in place (before any handler formats it)."""
    try:
        message = record.getMessage()
    except Exception:  # a malformed record: logging reports it as it would have
        return
    if message != (redacted := _redact_log(message)):
        record.msg, record.args = redacted, ()
    if record.exc_info and not record.exc_text:
        record.exc_text = _redact_log(logging.Formatter().formatException(record.exc_info))
    if record.stack_info:
        record.stack_info = _redact_log(record.stack_info)


def install_log_redaction(secrets: Iterable[str | None] = ()) -> None:
    """Redact every log record of this process (and of the processes it forks) as it is made, at
    every level and from every logger (botocore's and urllib3's included): a password, an S3
    ``Authorization`` header, signature or access key id that reaches a log line through an error
    message, a URL or a DEBUG dump of a request is ``***`` in the log, tracebacks included.

    ``secrets``: literal values (a worker's S3 access key id and secret key) masked wherever they
    appear in a record; None, empty and values under six characters are skipped. Calling again adds
    secrets and installs nothing twice."""
    _LOG_SECRETS.update(s for s in secrets if s and len(s) >= _MIN_LITERAL)
    make = logging.getLogRecordFactory()
    if getattr(make, "undream_redacts", False):
        return

    def factory(*args: Any, **kwargs: Any) -> logging.LogRecord:
        record = make(*args, **kwargs)
        _redact_record(record)
        return record

    factory.undream_redacts = True  # type: ignore[attr-defined]
    logging.setLogRecordFactory(factory)
