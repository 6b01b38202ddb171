"""``undream export``: a texture at its real size (metres per texel from the mesh's 3D and UV areas) or a
chosen width, at a DPI, as PNG and PDF with the colour profile embedded, and a preview (docs/printing.md)."""
from __future__ import annotations

import json
import math

import numpy as np
import pikepdf
import pytest
import yaml
from click.testing import CliRunner
from PIL import Image

from undream.cli import main
from undream.errors import PrintError
from undream.printing.export import print_size
from undream.printing.profiles import default_profile, srgb_profile
from undream.printing.size import texel_size
from undream.settings import load_local

PROFILE = default_profile(load_local().undream_cache)
needs_profile = pytest.mark.skipif(not PROFILE.is_file(), reason=f"the CMYK profile is not in {PROFILE}: run "
                                   "./deploy/setup.sh (or .venv/bin/python deploy/fetch_profiles.py)")
RECT = (np.array([[0, 0, 0], [1, 0, 0], [1, 0.5, 0], [0, 0.5, 0]], float), np.array([[0, 1, 2], [0, 2, 3]]),
        np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float))  # 1 m × 0.5 m, one chart over all of UV


def test_metres_per_texel_known_answers():
    size = texel_size(*RECT, (100, 50))
    assert size.metres == pytest.approx(0.01) and (size.width_m, size.height_m) == pytest.approx((1.0, 0.5))
    assert texel_size(*RECT, (100, 50), uv_scale=(2, 2)).width_m == pytest.approx(0.5)  # repeated twice
    assert texel_size(*RECT, (100, 50), scale=3.0).width_m == pytest.approx(3.0)
    half_uv = RECT[2] * 0.5  # the same surface on a quarter of the texture: 4× fewer metres a texel... per side 2×
    assert texel_size(RECT[0], RECT[1], half_uv, (100, 50)).metres == pytest.approx(0.02)
    with pytest.raises(PrintError, match=r"no triangle has both a surface and a UV area"):
        texel_size(RECT[0], RECT[1], np.zeros((4, 2)), (100, 50))


def test_print_sizes_and_their_refusals():
    size = texel_size(*RECT, (100, 50))
    p = print_size(size, (100, 50), 254)
    assert p.pixels == (10000, 5000) and p.points == pytest.approx((1 / 0.0254 * 72, 0.5 / 0.0254 * 72))
    p = print_size(size, (100, 50), 100, width_cm=20)
    assert (p.width_m, p.height_m, p.pixels) == (0.2, 0.1, (787, 394))
    for dpi in (0, -3, float("nan"), 5000, True):
        with pytest.raises(PrintError, match=r"^--dpi: must be a number of dots per inch in \(0, 4800\], got"):
            print_size(size, (100, 50), dpi)
    with pytest.raises(PrintError, match=r"^--width-cm: must be a width in centimetres > 0, got 0"):
        print_size(size, (100, 50), 300, width_cm=0)
    with pytest.raises(PrintError, match=r"more than 100,000,000; give a lower --dpi or a smaller --width-cm"):
        print_size(size, (100, 50), 1200)


# -- the command ------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def run_dir(tmp_path_factory, mi):
    """A finished tiny run on a sphere (r 0.5 m, a 16×8 texture), gamut default where setup fetched it."""
    from farm_support import make_scene, make_victim, run_config

    base = tmp_path_factory.mktemp("export")
    scene, victim = make_scene(base / "scene", n_frames=2, size=24), make_victim(base / "victim")
    config = run_config(scene, victim, name="export", steps=1, holdout="none",
                        gamut="default" if PROFILE.is_file() else "none")
    (base / "run.yaml").write_text(yaml.safe_dump(config))
    res = CliRunner().invoke(main, ["run", str(base / "run.yaml"), "--out", str(base / "run"), "--no-progress"])
    assert res.exit_code == 0, res.output
    return base / "run"


def _export(*args):
    return CliRunner().invoke(main, ["export", *map(str, args), "--no-progress"])


@needs_profile
def test_a_run_exports_at_its_real_size_in_the_printers_cmyk(run_dir, tmp_path):
    res = _export(run_dir, "--out", tmp_path / "print", "--dpi", 50, "--preview-frames", 2, "--preview-spp", 4)
    assert res.exit_code == 0, res.output
    record = json.loads((tmp_path / "print" / "export.json").read_text())
    # the sphere's area (4πr², r = 0.5 m) over its chart's UV area (all of [0, 1]² less half of each of its 24
    # rows' strips at the poles, where the triangles fan out), per texel
    side = math.sqrt(math.pi / (23 / 24) / (16 * 8))
    assert record["width_cm"] == pytest.approx(16 * side * 100, rel=0.005)  # 48×24 facets: 0.2 % short
    assert record["height_cm"] == pytest.approx(8 * side * 100, rel=0.005)
    with Image.open(tmp_path / "print" / "texture_print.png") as png:
        assert png.info["dpi"] == pytest.approx((50, 50), rel=1e-3)  # pHYs: whole pixels a metre and png.info["icc_profile"] == srgb_profile()
        assert png.size == (round(record["width_cm"] / 2.54 * 50), round(record["height_cm"] / 2.54 * 50))
    pdf = pikepdf.open(tmp_path / "print" / "texture_print.pdf")
    (page,) = pdf.pages
    assert [float(x) for x in page.mediabox] == pytest.approx(
        [0, 0, record["width_cm"] / 2.54 * 72, record["height_cm"] / 2.54 * 72], abs=0.01)
    (image,) = [pikepdf.PdfImage(x) for x in page.Resources.XObject.values()]
    kind, icc = image.obj.ColorSpace
    assert kind == "/ICCBased" and icc.N == 4 and icc.read_bytes() == PROFILE.read_bytes()
    with Image.open(tmp_path / "print" / "preview.png") as preview:
        assert preview.size == (48, 24)  # two 24-px frames side by side


def test_a_texture_file_exports_at_the_width_asked_for(run_dir, tmp_path):
    meta = json.loads((run_dir / "metadata.json").read_text())
    texture = np.random.default_rng(0).random((8, 16, 3)).astype(np.float32)
    np.save(tmp_path / "t.npy", texture)
    res = _export(tmp_path / "t.npy", "--scene", meta["scene_dir"], "--out", tmp_path / "print", "--dpi", 72,
                  "--width-cm", 25.4, "--preview-frames", 0, "--resample", "nearest")
    assert res.exit_code == 0, res.output
    with Image.open(tmp_path / "print" / "texture_print.png") as png:
        assert png.size == (720, 360) and png.info["dpi"] == pytest.approx((72, 72), rel=1e-3)
        blocks = np.asarray(png)
    assert np.array_equal(blocks[::45, ::45], np.rint(texture * 255).astype(np.uint8))  # nearest: 45-px blocks
    pdf = pikepdf.open(tmp_path / "print" / "texture_print.pdf")
    page = pdf.pages[0]
    assert [float(x) for x in page.mediabox] == pytest.approx([0, 0, 720, 360], abs=0.01)  # 10 × 5 inches
    (image,) = page.Resources.XObject.values()
    assert image.ColorSpace[0] == "/ICCBased" and image.ColorSpace[1].N == 3  # no profile asked for: sRGB
    assert not (tmp_path / "print" / "preview.png").exists()


def test_bad_exports_are_one_line_and_write_nothing(run_dir, tmp_path):
    out = tmp_path / "print"
    cases = [
        ((tmp_path / "missing", "--out", out), r"SOURCE .*missing: no such run folder or texture file"),
        ((tmp_path, "--out", out), r"SOURCE .*: not an output folder of `undream run`"),
        ((run_dir, "--out", out, "--dpi", 0), r"--dpi: must be a number of dots per inch in \(0, 4800\], got 0"),
        ((run_dir, "--out", out, "--width-cm", -2), r"--width-cm: must be a width in centimetres > 0"),
        ((run_dir, "--out", out, "--profile", "x.png"), r"--profile: must be default .*, got 'x.png'"),
        ((run_dir, "--out", out, "--profile", tmp_path / "none.icc"), r"--profile: .*none\.icc: no such profile"),
    ]
    np.save(tmp_path / "t.npy", np.zeros((8, 16, 3), np.float32))
    cases.append(((tmp_path / "t.npy", "--out", out), r"needs --scene"))
    np.save(tmp_path / "small.npy", np.zeros((4, 4, 3), np.float32))
    meta = json.loads((run_dir / "metadata.json").read_text())
    cases.append(((tmp_path / "small.npy", "--scene", meta["scene_dir"], "--out", out),
                  r"texture: 4×4 texels, but the scene's texture is 16×8"))
    for args, message in cases:
        res = _export(*args)
        assert res.exit_code == 2, (args, res.output)
        lines = res.output.strip().splitlines()
        assert len(lines) == 1 and __import__("re").search(message, lines[0]), (args, res.output)
        assert not out.exists()


def test_force_replaces_only_an_earlier_export(run_dir, tmp_path):
    out = tmp_path / "print"
    assert _export(run_dir, "--out", out, "--dpi", 10, "--preview-frames", 0).exit_code == 0
    res = _export(run_dir, "--out", out, "--dpi", 10, "--preview-frames", 0)
    assert res.exit_code == 2 and "already exists (use --force to replace it)" in res.output
    assert _export(run_dir, "--out", out, "--dpi", 20, "--preview-frames", 0, "--force").exit_code == 0
    assert json.loads((out / "export.json").read_text())["dpi"] == 20
    mine = tmp_path / "thesis"
    mine.mkdir()
    (mine / "chapter.tex").write_text("mine")
    res = _export(run_dir, "--out", mine, "--dpi", 10, "--force")
    assert res.exit_code == 2 and "--force only replaces a folder that `undream export` wrote" in res.output
    assert [p.name for p in mine.iterdir()] == ["chapter.tex"]
    (tmp_path / "file").write_text("x")
    res = _export(run_dir, "--out", tmp_path / "file", "--dpi", 10)
    assert res.exit_code == 2 and len(res.output.strip().splitlines()) == 1
