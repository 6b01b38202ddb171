"""The ``gamut`` field of a run config: ``default``, ``none`` or a CMYK ICC profile's path.

No heavy imports: a profile file is checked by its ICC header alone (the 128
bytes every ICC profile starts with: ``acsp`` at byte 36, the data colour
space at 16, the device class at 12); littleCMS opens it later
(:func:`undream.printing.gamut.load_gamut`). Errors are one line naming the field.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

from undream.errors import SpecError

GAMUT_WORDS = ("default", "none")  # default: the CMYK profile setup fetched (undream.printing.profiles)
PROFILE_SUFFIXES = (".icc", ".icm")
VALID = "default (the CMYK profile setup fetched), none, or the path of a CMYK printer profile (.icc or .icm)"


def check_gamut(value: Any, field: str = "gamut") -> str:
    """``value`` if it is ``default``, ``none`` or a path ending in .icc/.icm (the file is not read here)."""
    if isinstance(value, str) and (value in GAMUT_WORDS or value.lower().endswith(PROFILE_SUFFIXES)):
        return value
    raise SpecError(f"{field}: must be {VALID}, got {value!r}")


def check_profile(path: str | Path, field: str = "gamut") -> Path:
    """``path`` if it is a readable ICC profile of a CMYK output device (a printer); else one-line SpecError."""
    path = Path(path)
    try:
        with path.open("rb") as f:
            head = f.read(128)
    except FileNotFoundError:
        raise SpecError(f"{field}: {path}: no such profile; give {VALID}") from None
    except OSError as err:
        raise SpecError(f"{field}: {path}: cannot read the profile ({err.strerror or err})") from None
    if len(head) < 128 or head[36:40] != b"acsp":
        raise SpecError(f"{field}: {path}: not an ICC profile (no 'acsp' signature in its header)")
    space, device = head[16:20].decode("latin-1").strip(), head[12:16].decode("latin-1").strip()
    if space != "CMYK":
        raise SpecError(f"{field}: {path}: a profile of {space or '?'} colours, not CMYK; give a CMYK printer profile")
    if device != "prtr":
        raise SpecError(f"{field}: {path}: a CMYK profile of device class {device or '?'!r}, not a printer's ('prtr')")
    return path
