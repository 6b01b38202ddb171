"""The CMYK profiles a run's ``gamut`` names, and the sRGB profile textures are written with.

``gamut: default`` is Ghostscript's default CMYK output profile, "Artifex CMYK
SWOP Profile" (Debian's ``libgs-common``, AGPL-3+), which
``deploy/fetch_profiles.py`` fetches at setup into ``CACHE_DIR/profiles``;
``CACHE_DIR`` is undream's cache folder (``LocalSettings.undream_cache``,
passed down from the edge). Errors are one-line :class:`SpecError` naming the field.
"""
from __future__ import annotations

from pathlib import Path

from PIL import ImageCms

from undream.errors import SpecError
from undream.spec.printing import check_gamut, check_profile

DEFAULT_PROFILE = Path("ghostscript") / "default_cmyk.icc"  # under profiles_dir(cache_dir)


def profiles_dir(cache_dir: str | Path) -> Path:
    """``CACHE_DIR/profiles``: where setup puts fetched print profiles."""
    return Path(cache_dir) / "profiles"


def default_profile(cache_dir: str | Path) -> Path:
    """The path of ``gamut: default``'s profile under ``cache_dir`` (it may not exist)."""
    return profiles_dir(cache_dir) / DEFAULT_PROFILE


def resolve_gamut(value: str, cache_dir: str | Path, field: str = "gamut") -> Path | None:
    """The CMYK profile a ``gamut`` value names, checked (:func:`undream.spec.printing.check_profile`):
    None for ``none``, the fetched default for ``default``, else the path itself."""
    check_gamut(value, field)
    if value == "none":
        return None
    if value == "default":
        path = default_profile(cache_dir)
        if not path.is_file():
            raise SpecError(f"{field}: default: the CMYK profile {path} is not there; ./deploy/setup.sh "
                            "fetches it (or .venv/bin/python deploy/fetch_profiles.py), or give a profile's path")
        return check_profile(path, field)
    return check_profile(Path(value).expanduser(), field)


def srgb_profile() -> bytes:
    """littleCMS's built-in sRGB profile as ICC bytes (what an exported sRGB texture embeds)."""
    return ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes()
