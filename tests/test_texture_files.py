"""Hostile texture files given to the command line: one line naming the file, nothing decoded or
allocated past what the header allows, nothing written (undream.scene.texture_file; issue 41).

Before: `undream evaluate` on a 0-byte .npy printed "undream: aborted" (numpy's EOFError, which click
takes for Ctrl-D), on a zero-size float .npy a ValueError traceback, on a .npy header claiming
112 GiB a MemoryError traceback, on a 100-byte PNG claiming 30000² pixels Pillow's
DecompressionBombError traceback; a 16-bit greyscale PNG was clipped (every value above 255 white).
"""
from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from PIL import Image

from farm_support import make_scene, write_yaml
from undream.cli import main


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def _png(path: Path, width: int, height: int, depth: int, colour: int, raw: bytes) -> Path:
    """A PNG written by hand: any header, whatever the data (colour 0 grey, 2 RGB, 4 grey+alpha, 6 RGBA)."""
    head = struct.pack(">IIBBBBB", width, height, depth, colour, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", head) + _chunk(b"IDAT", zlib.compress(raw))
                     + _chunk(b"IEND", b""))
    return path


def _rows(array: np.ndarray) -> bytes:
    """PNG scanlines (filter 0) of ``array`` (H×W or H×W×C, uint8 or uint16 written big-endian)."""
    dtype = ">u2" if array.dtype == np.uint16 else "u1"
    return b"".join(b"\0" + row.astype(dtype).tobytes() for row in array.reshape(array.shape[0], -1))


def _npy_header(path: Path, header: str, version: int = 1, data: bytes = b"") -> Path:
    text = header + " " * (63 - (12 + len(header)) % 64) + "\n"
    size = struct.pack("<H" if version == 1 else "<I", len(text))
    path.write_bytes(b"\x93NUMPY" + bytes([version, 0]) + size + text.encode() + data)
    return path


def _bytes(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


def _grey16() -> np.ndarray:
    return np.linspace(0, 65535, 8 * 16).round().astype(np.uint16).reshape(8, 16)


HOSTILE = {  # file name → (writer, what the one line says)
    "empty.npy": (lambda p: _bytes(p, b""), "an empty file (0 bytes)"),
    "zero_size.npy": (lambda p: np.save(p, np.zeros((0, 16, 3), np.float32)) or p, "16×0 pixels"),
    "huge_shape.npy": (lambda p: _npy_header(p, "{'descr': '<f4', 'fortran_order': False, "
                                                "'shape': (100000, 100000, 3), }", data=b"\0" * 64),
                       "100000×100000 pixels; a texture file may hold at most 67108864"),
    "huge_header.npy": (lambda p: _npy_header(p, "{'descr': '<f4', 'fortran_order': False, 'shape': (8, 16, 3), }"
                                                 + " " * 200_000, version=2),
                        "a .npy header longer than 10000 bytes"),
    "cut_short.npy": (lambda p: _bytes(p, _npy_bytes(np.zeros((8, 16, 3), np.float32))[:300]), "cut short"),
    "object.npy": (lambda p: _npy_header(p, "{'descr': '|O', 'fortran_order': False, 'shape': (8, 16, 3), }"),
                   "dtype object"),
    "two_channels.npy": (lambda p: np.save(p, np.zeros((8, 16, 2), np.float32)) or p, "shape (8, 16, 2), not H×W×3"),
    "four_channels.npy": (lambda p: np.save(p, np.zeros((8, 16, 4), np.uint8)) or p, "shape (8, 16, 4), not H×W×3"),
    "bomb.png": (lambda p: _png(p, 30000, 30000, 8, 2, b"\0" * 100), "at most 67108864 pixels (8192×8192)"),
    "big.png": (lambda p: _png(p, 9000, 9000, 1, 0, b"\0" * 100), "9000×9000 pixels; a texture file may hold at most"),
    "truncated.png": (lambda p: _bytes(p, _png(p, 16, 8, 16, 0, _rows(_grey16())).read_bytes()[:60]),
                      "unreadable image"),
    "not_a.png": (lambda p: _bytes(p, b"GIF89a but not really"), "not an image Pillow can read"),
    "transparent.png": (lambda p: Image.fromarray(np.zeros((8, 16, 4), np.uint8)).save(p) or p,
                        "128 transparent pixel(s)"),
}


def _npy_bytes(array: np.ndarray) -> bytes:
    import io

    buf = io.BytesIO()
    np.save(buf, array)
    return buf.getvalue()


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return make_scene(tmp_path_factory.mktemp("textures") / "scene", n_frames=2, size=16)


@pytest.mark.parametrize("case", sorted(HOSTILE))
def test_a_hostile_texture_given_to_evaluate_is_one_line_naming_it(case, scene, tmp_path):
    write, needle = HOSTILE[case]
    texture = write(tmp_path / case)
    res = CliRunner().invoke(main, ["evaluate", str(texture), str(scene), "--victim", "bundled:classifier",
                                    "--json", str(tmp_path / "rows.json")])
    lines = res.output.strip().splitlines()
    assert res.exit_code == 2 and len(lines) == 1, res.output[-3000:]
    assert lines[0].startswith(f"undream: error: TEXTURE {texture}: ") and needle in lines[0], lines[0]
    assert not (tmp_path / "rows.json").exists()


SPEC = {"name": "ball", "frames": 2,
        "camera": {"fov": 40, "resolution": [16, 16], "path": {"type": "orbit", "radius": 4, "height": 1}},
        "object": {"path": {"type": "static", "position": [0, 0, 0]}}}


def _spec(tmp_path: Path, init: Path) -> Path:
    asset = {"name": "ball", "mesh": "builtin:sphere", "texture": {"resolution": [16, 8], "init": str(init)}}
    return write_yaml(tmp_path / "spec.yaml", {**SPEC, "object": {**SPEC["object"], "asset": asset}})


@pytest.mark.parametrize("case", ["bomb.png", "big.png", "truncated.png", "not_a.png", "transparent.png",
                                  "empty.npy"])
def test_a_hostile_starting_texture_given_to_init_is_one_line_naming_it(case, tmp_path):
    write, needle = HOSTILE[case]
    texture = write(tmp_path / case)
    res = CliRunner().invoke(main, ["init", str(_spec(tmp_path, texture)), "--out", str(tmp_path / "scene")])
    lines = res.output.strip().splitlines()
    assert res.exit_code == 2 and len(lines) == 1, res.output[-3000:]
    assert f"{texture}: " in lines[0] and needle in lines[0] and "asset.texture.init" in lines[0], lines[0]
    assert not (tmp_path / "scene").exists()


def test_a_16_bit_png_is_read_scaled_not_clipped(tmp_path):
    """Grey 16-bit: v / 257 rounded (65535 → 255, 32896 → 128); Pillow's convert("RGB") had made
    every value above 255 white. 16-bit RGB: scaled by Pillow already."""
    from scheduler.evaluate import read_texture

    grey = _png(tmp_path / "grey16.png", 16, 8, 16, 0, _rows(_grey16()))
    got = read_texture(grey)
    want = np.round(_grey16() / 257.0) / 255.0
    assert got.shape == (8, 16, 3)
    np.testing.assert_allclose(got[..., 1], want, atol=1e-6)
    assert 0.2 < got.mean() < 0.8  # clipped, all but the first pixel were 1.0
    rgb = np.zeros((8, 16, 3), np.uint16)
    rgb[..., 0], rgb[..., 1], rgb[..., 2] = 65535, 32896, 0
    got = read_texture(_png(tmp_path / "rgb16.png", 16, 8, 16, 2, _rows(rgb)))
    np.testing.assert_allclose(got[0, 0], [1.0, 128 / 255, 0.0], atol=1e-6)


def test_init_starts_from_a_16_bit_png_scaled(tmp_path):
    grey = _png(tmp_path / "grey16.png", 16, 8, 16, 0, _rows(_grey16()))
    res = CliRunner().invoke(main, ["init", str(_spec(tmp_path, grey)), "--out", str(tmp_path / "scene"),
                                    "--no-progress"])
    assert res.exit_code == 0, res.output[-3000:]
    written = np.asarray(Image.open(tmp_path / "scene" / "textures" / "adv_texture.png"))
    np.testing.assert_array_equal(written[..., 0], np.round(_grey16() / 257.0).astype(np.uint8))
