"""``undream init``: the scene directory, its agreement with the sequence, and bad input."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from PIL import Image

from conftest import EXAMPLES
from projection import centroid, load, visible_mask
from undream.cli import main
from undream.scenedir.init import InitOptions, init_scene
from undream.scenedir.verify import mask_box, read_mask
from undream.spec import load_sequence

MIN_PIXELS = 12  # frames where the object covers fewer pixels say little about a centroid


def test_examples_are_enough():
    assert len([p for p in EXAMPLES if p.suffix == ".yaml"]) >= 4
    assert any(p.suffix == ".json" for p in EXAMPLES)


def test_layout_of_every_example(example_scenes):
    for name, d in example_scenes.items():
        seq = load_sequence(d / "sequence.json")
        assert len(seq.frames) >= 8, name
        meta = json.loads((d / "metadata.json").read_text())
        assert meta["seed"] == seq.seed and meta["versions"]["mitsuba"] and meta["spec"]
        for f in seq.frames:
            for rel in (f"frames/sim_{f.index:04d}.xml", f"frames/grad_{f.index:04d}.xml",
                        f"verify/white_{f.index:04d}.png", f"verify/mask_{f.index:04d}.png"):
                assert (d / rel).is_file(), f"{name}: {rel}"
        assert (d / "verify" / "contact_sheet.png").is_file()
        assert (d / "meshes" / "object.ply").is_file()
        assert not list(d.parent.glob(f".{name}.tmp-*")), "temporary directory left behind"


def test_the_grouped_verification_renders_equal_each_frame_loaded_alone(example_scenes, mi):
    """The init renders its frames from one loaded scene per group (render_frames); each white
    render and mask is that of the frame's own scene loaded and rendered alone."""
    from undream.scene.layout import frame_xml
    from undream.scene.mitsuba_scene import ScenePaths, scene_dict
    from undream.scene.xml import to_xml
    from undream.scenedir.verify import render_frames, render_mask, render_white

    checked = 0
    for name, d in example_scenes.items():
        seq = load_sequence(d / "sequence.json")
        frames = seq.frames[::3]
        for f in frames:  # the mask scenes, as the init writes them while it verifies
            frame_xml(d, "mask", f.index).write_text(to_xml(scene_dict(seq, f, ScenePaths(".."), "mask"), {"spp": 64}))
        try:
            for (index, white, mask), f in zip(render_frames(mi, d, [f.index for f in frames], 4), frames, strict=True):
                assert index == f.index
                alone = render_white(mi, frame_xml(d, "sim", index), 4)
                # The same samples, but a frame alone merges its meshes and the group's scene keeps them
                # apart: where the object moves, a few paths (up to 1.4 % of pixels) go another way after
                # a rounding difference (mean |difference| up to 2e-5 measured); the neighbouring frame's
                # render differs from a frame's by 4e-4 or more in every example whose frames differ.
                assert np.abs(white - alone).mean() < 1e-4, f"{name} frame {index}"
                np.testing.assert_array_equal(mask, render_mask(mi, seq, f, d, 4), err_msg=f"{name} frame {index}")
                checked += 1
        finally:
            for f in frames:
                frame_xml(d, "mask", f.index).unlink()
    assert checked >= 20


def test_mask_centroid_agrees_with_independent_projection(example_scenes):
    checked = 0
    for name, d in example_scenes.items():
        seq = load(d)
        for f in seq["frames"]:
            mask = read_mask(d, f["index"])
            expect = visible_mask(d, f, seq)
            assert (mask.sum() >= MIN_PIXELS) == (expect.sum() >= MIN_PIXELS) or abs(
                int(mask.sum()) - int(expect.sum())) < 6, f"{name} frame {f['index']}"
            if expect.sum() < MIN_PIXELS:
                continue
            err = np.linalg.norm(centroid(mask) - centroid(expect))
            assert err <= 1.5, f"{name} frame {f['index']}: mask centroid off by {err:.2f} px"
            checked += 1
    assert checked >= 30


def test_mask_box_known_answer():
    m = np.zeros((8, 10), bool)
    m[2:5, 3:7] = True
    assert mask_box(m) == (3.0, 2.0, 7.0, 5.0)
    assert mask_box(np.zeros((4, 4), bool)) is None


def test_mask_box_of_a_saved_mask(example_scenes):
    d = next(iter(example_scenes.values()))
    index = load_sequence(d / "sequence.json").frames[0].index
    mask = read_mask(d, index)
    x0, y0, x1, y1 = mask_box(mask)
    assert mask[int(y0):int(y1), int(x0):int(x1)].sum() == mask.sum() > 0


def test_every_xml_loads(example_scenes, mi):
    from undream.render.haze import register

    register(mi)  # frames in fog, rain or snow name undream's own integrator (docs/scenes.md)
    for name, d in example_scenes.items():
        for xml in sorted((d / "frames").glob("*.xml")):
            scene = mi.load_file(str(xml), spp=1)
            assert any(s.id() == "object" for s in scene.shapes()), xml


def test_refuses_to_overwrite_without_force(example_scenes, tmp_path):
    out = tmp_path / "scene"
    src = EXAMPLES[0]
    init_scene(src, out, InitOptions(verify_spp=1))
    marker = out / "marker"
    marker.write_text("mine")
    res = CliRunner().invoke(main, ["init", str(src), "--out", str(out), "--no-progress", "--verify-spp", "1"])
    assert res.exit_code == 2 and "already exists" in res.output and marker.exists()
    res = CliRunner().invoke(main, ["init", str(src), "--out", str(out), "--force", "--no-progress",
                                    "--verify-spp", "1"])
    assert res.exit_code == 0, res.output
    assert not marker.exists() and (out / "sequence.json").is_file()
    assert not list(tmp_path.glob(".scene.*"))


def test_failure_midway_leaves_nothing(tmp_path, monkeypatch):
    import undream.scenedir.init as init_module

    def boom(*a, **k):
        raise RuntimeError("renderer died")

    monkeypatch.setattr(init_module, "render_frames", boom)  # the name init renders its frames with
    with pytest.raises(RuntimeError):
        init_scene(EXAMPLES[0], tmp_path / "scene", InitOptions(verify_spp=1))
    assert list(tmp_path.iterdir()) == []


def test_texture_resolution_is_width_height(tmp_path):
    from undream.scenedir.init import texture_from_spec
    from undream.spec import TextureParam

    tex = TextureParam(resolution=(8, 4), init=(0.2, 0.4, 0.6))
    assert tex.shape == (4, 8, 3)
    assert texture_from_spec(tex, None).shape == (4, 8, 3)
    Image.new("RGB", (3, 5), (255, 0, 0)).save(tmp_path / "red.png")
    img = texture_from_spec(TextureParam(resolution=(8, 4), init="red.png"), tmp_path)
    assert img.shape == (4, 8, 3) and np.allclose(img, [1.0, 0.0, 0.0])
