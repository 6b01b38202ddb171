"""``undream report``: a finished run or a sweep as a static HTML page with PNG charts and CSV tables.

Read from the store (a run's evaluation frames, predictions, textures and
iteration records; a sweep's runs), drawn with matplotlib and PIL, written
atomically (:mod:`undream.report.build`). Modules: :mod:`~undream.report.data`
(a run as plain data), :mod:`~undream.report.seen` (texels some frame sees,
from the scene's visibility), :mod:`~undream.report.tables` (rows and CSV),
:mod:`~undream.report.sheet` (the contact sheet), :mod:`~undream.report.charts`
(charts and the texture panel), :mod:`~undream.report.page` (HTML). The page
needs no server, no network and no JavaScript.
"""
from __future__ import annotations

from undream.report.build import MARKER, Target, build_report, is_report

__all__ = ["MARKER", "Target", "build_report", "is_report"]
