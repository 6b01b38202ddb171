"""Texture files a user gives: an image (a spec's ``asset.texture.init``, ``undream evaluate``'s
TEXTURE) or a ``.npy`` array, read only after their headers say they are sane.

Every refusal is one :class:`~undream.errors.SpecError` line that starts with the name the caller
gives (``TEXTURE path``, a path) and says what is wrong and what is valid: an empty file, a header
claiming more than :data:`MAX_TEXTURE_PIXELS` pixels (a 100-byte PNG claiming 30000² pixels, a
``.npy`` claiming 112 GiB: refused before anything is decoded or allocated), a ``.npy`` whose header
is too long or whose data is cut short, a dtype or channel count that is no RGB texture, an image with
transparent pixels. A 16-bit greyscale PNG is scaled to 8 bits (Pillow's ``convert("RGB")`` clipped
every value above 255 to white); 16-bit RGB PNGs Pillow already reads scaled to 8 bits.
"""
from __future__ import annotations

import struct
import warnings
import zlib
from pathlib import Path

import numpy as np
from PIL import Image

from undream.errors import SpecError

MAX_SIDE = 8192  # texels: the largest texture resolution a spec takes (TextureParam.resolution)
MAX_TEXTURE_PIXELS = MAX_SIDE * MAX_SIDE  # pixels of any texture file, checked from its header
NPY_MAX_HEADER = 10_000  # bytes of a .npy header (numpy's own default limit)

# What Pillow's decoders raise on a corrupt or hostile file.
_DECODE_ERRORS = (OSError, ValueError, SyntaxError, EOFError, struct.error, zlib.error, Image.DecompressionBombError)


def _size(path: Path, name: str) -> int:
    try:
        size = path.stat().st_size
    except OSError as err:
        raise SpecError(f"{name}: cannot read ({err.strerror})") from None
    if size == 0:
        raise SpecError(f"{name}: an empty file (0 bytes)")
    return size


def _pixels(name: str, width: int, height: int) -> None:
    if width < 1 or height < 1:
        raise SpecError(f"{name}: {width}×{height} pixels; a texture has at least one pixel")
    if width * height > MAX_TEXTURE_PIXELS:
        raise SpecError(f"{name}: {width}×{height} pixels; a texture file may hold at most "
                        f"{MAX_TEXTURE_PIXELS} pixels ({MAX_SIDE}×{MAX_SIDE})")


def read_image_rgb(path: Path, name: str) -> Image.Image:
    """The image file ``path`` as an 8-bit RGB Pillow image (sRGB, as stored), decoded only after its
    header's size passed :data:`MAX_TEXTURE_PIXELS`. Greyscale is repeated over the three channels,
    a palette expanded, an alpha channel dropped only when every pixel is opaque, a 16-bit greyscale
    image scaled to 8 bits (v / 257, rounded). ``name``: how errors name the file."""
    _size(path, name)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            image = Image.open(path)
    except FileNotFoundError:
        raise SpecError(f"{name}: file not found") from None
    except Image.UnidentifiedImageError:
        raise SpecError(f"{name}: not an image Pillow can read") from None
    except (Image.DecompressionBombError, Image.DecompressionBombWarning) as err:  # a header's size, before any pixel
        raise SpecError(f"{name}: refused unread ({_first_line(err)}); a texture file may hold at most "
                        f"{MAX_TEXTURE_PIXELS} pixels ({MAX_SIDE}×{MAX_SIDE})") from None
    except _DECODE_ERRORS as err:
        raise SpecError(f"{name}: unreadable image ({_first_line(err)})") from None
    with image:
        _pixels(name, *image.size)
        try:
            image.load()
            return _to_rgb(image, name)
        except SpecError:
            raise
        except (*_DECODE_ERRORS, MemoryError) as err:
            raise SpecError(f"{name}: unreadable image ({_first_line(err)})") from None


def _to_rgb(image: Image.Image, name: str) -> Image.Image:
    if image.mode in ("I;16", "I;16B", "I;16L", "I"):  # 16-bit greyscale (PNG), or 32-bit integer
        values = np.asarray(image).astype(np.int64)
        top = 65535 if image.mode.startswith("I;16") or values.max(initial=0) <= 65535 else None
        if top is None or values.min(initial=0) < 0:
            raise SpecError(f"{name}: integer pixels outside 0-65535 (mode {image.mode}); give an 8- or 16-bit image")
        grey = np.round(values / 257.0).astype(np.uint8)
        return Image.fromarray(np.repeat(grey[..., None], 3, axis=2), mode="RGB")
    if image.mode == "F":
        raise SpecError(f"{name}: floating-point pixels (mode F); give an 8- or 16-bit image, or a .npy")
    if "A" in image.getbands() or "transparency" in image.info:
        rgba = image.convert("RGBA")
        alpha = np.asarray(rgba)[..., 3]
        if (alpha < 255).any():
            raise SpecError(f"{name}: {int((alpha < 255).sum())} transparent pixel(s) (alpha below 255); a "
                            "texture has no alpha: flatten the image onto a background first")
        return rgba.convert("RGB")
    return image.convert("RGB")


def read_npy_texture(path: Path, name: str) -> np.ndarray:
    """The ``.npy`` file ``path`` as its H×W×3 array (uint8, or floats as stored), read only after its
    header says a sane shape and dtype and the file holds every byte of it; no pickles."""
    size = _size(path, name)
    try:
        with open(path, "rb") as f:
            version = np.lib.format.read_magic(f)
            if version == (1, 0):
                shape, fortran, dtype = np.lib.format.read_array_header_1_0(f, max_header_size=NPY_MAX_HEADER)
            else:
                shape, fortran, dtype = np.lib.format.read_array_header_2_0(f, max_header_size=NPY_MAX_HEADER)
            offset = f.tell()
    except (OSError, ValueError, SyntaxError, EOFError) as err:
        if "max_header_size" in str(err):
            raise SpecError(f"{name}: a .npy header longer than {NPY_MAX_HEADER} bytes (a texture's takes about "
                            "100); refused unread") from None
        raise SpecError(f"{name}: not a .npy array numpy can read ({_first_line(err)})") from None
    if dtype.hasobject or dtype.kind not in "uif":
        raise SpecError(f"{name}: dtype {dtype}; a texture is uint8, or floats in [0, 1]")
    if len(shape) != 3 or shape[2] != 3:
        raise SpecError(f"{name}: shape {tuple(shape)}, not H×W×3")
    _pixels(name, shape[1], shape[0])
    need = shape[0] * shape[1] * 3 * dtype.itemsize
    if size - offset < need:
        raise SpecError(f"{name}: cut short: its header says {tuple(shape)} {dtype} ({need} bytes of data), "
                        f"the file holds {size - offset}")
    try:
        return np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError, MemoryError) as err:
        raise SpecError(f"{name}: unreadable ({_first_line(err)})") from None


def _first_line(err: BaseException) -> str:
    text = " ".join(str(err).split()) or type(err).__name__
    return text if len(text) <= 200 else text[:200] + "…"
