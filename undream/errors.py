"""The undream exception hierarchy.

Every error raised on bad input is an :class:`UndreamError`; its message names
the file or field, the offending value and what would be valid, on one line.
"""
from __future__ import annotations


class UndreamError(Exception):
    """Base class of every error undream raises on purpose."""


class SpecError(UndreamError, ValueError):
    """A spec, config or sequence field is missing or invalid."""


class AssetError(UndreamError):
    """A mesh or texture file is missing, unreadable or unusable."""


class BridgeError(UndreamError):
    """A simulator export could not be converted to the canonical form."""


class RenderError(UndreamError):
    """Mitsuba failed to load or render a scene."""


class VictimError(UndreamError):
    """A victim model could not be loaded or was given bad input."""


class MetricsError(UndreamError, ValueError):
    """Metric inputs are malformed (shapes, labels, empty where not allowed)."""


class AttackError(UndreamError, ValueError):
    """An attack was given a bad texture, gradient, loss or state."""


class DatasetError(UndreamError, ValueError):
    """A dataset of the bundled victims could not be made or read (bad config, missing or corrupt files)."""


class StoreError(UndreamError):
    """The run store could not be read or written."""


class PrintError(UndreamError, ValueError):
    """A texture cannot be projected into a printer's gamut or exported for print (bad texture, size, DPI)."""


def already_exists(path: object) -> SpecError:
    """The error for an output ``path`` that exists and is replaced only on request (``--force``)."""
    return SpecError(f"{path}: already exists (use --force to replace it)")


def where(path: str | None, field: str | None) -> str:
    """Format the 'file: field' prefix used in error messages."""
    parts = [p for p in (path, field) if p]
    return ": ".join(parts)
