"""Meshes: built-in assets' geometry and UV atlases, PLY I/O, and loading users' files through Mitsuba."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from undream.errors import AssetError
from undream.scene.builtin import BUILTINS, asset_mesh, box, builtin_mesh, cylinder
from undream.scene.mesh import Mesh, concat_meshes, load_mesh_file, read_ply, uv_to_texel, write_ply
from undream.spec import Asset

NAMES = sorted(BUILTINS)
# Parts of the stop sign, for scenes whose object is the plate alone (its box a COCO "stop sign" box)
# and whose pole is an actor: smaller meshes than a whole object, and the plate hangs at 1.375 m.
PARTS = {"stop_sign_plate": 1.375, "sign_pole": 0.0}

# Documented bounds (metres): (min xyz, max xyz).
BOUNDS = {
    "sphere": ((-0.5, 0.0, -0.5), (0.5, 1.0, 0.5)),
    "trash_bin": ((-0.31, 0.0, -0.31), (0.31, 1.0, 0.31)),
    "car": ((-0.9, 0.0, -2.1), (0.9, 1.5, 2.1)),
    "umbrella": ((-1.0, 0.0, -1.0), (1.0, 2.26, 1.0)),
    "traffic_cone": ((-0.2, 0.0, -0.2), (0.2, 0.7, 0.2)),
    "stop_sign": ((-0.375, 0.0, -0.03), (0.375, 2.125, 0.051)),
    "stop_sign_plate": ((-0.375, 1.375, 0.031), (0.375, 2.125, 0.051)),
    "sign_pole": ((-0.03, 0.0, -0.03), (0.03, 2.1, 0.03)),
    "pedestrian": ((-0.31, 0.0, -0.12), (0.31, 1.76, 0.12)),
}

# The main visible surface of each built-in, selected from face centroids c and unit normals n.
MAIN = {
    "sphere": lambda c, n: np.ones(len(c), bool),
    "pedestrian": lambda c, n: (n[:, 2] > 0.5) & (np.abs(c[:, 0]) < 0.21) & (c[:, 1] > 0.87) & (c[:, 1] < 1.47),
    "trash_bin": lambda c, n: (np.abs(n[:, 1]) < 0.5) & (c[:, 1] < 0.92),
    "car": lambda c, n: (np.abs(n[:, 0]) > 0.99) & (np.abs(np.abs(c[:, 0]) - 0.88) < 1e-3),
    "umbrella": lambda c, n: (n[:, 1] > 0.3) & (c[:, 1] > 1.79) & (np.hypot(c[:, 0], c[:, 2]) > 0.021),
    "traffic_cone": lambda c, n: (c[:, 1] > 0.03) & (np.abs(n[:, 1]) < 0.9),
    "stop_sign": lambda c, n: (n[:, 2] > 0.99) & (c[:, 2] > 0.05),
    "stop_sign_plate": lambda c, n: (n[:, 2] > 0.99) & (c[:, 2] > 0.05),
    "sign_pole": lambda c, n: np.abs(n[:, 1]) < 0.5,
}


@pytest.fixture(scope="module", params=NAMES)
def built(request: pytest.FixtureRequest) -> tuple[str, Mesh]:
    return request.param, builtin_mesh(request.param)


@pytest.fixture(scope="module")
def mi():  # noqa: ANN201 - the mitsuba module
    pytest.importorskip("mitsuba")
    from undream.variant import mitsuba
    return mitsuba()


def _uv_cross(m: Mesh) -> np.ndarray:
    """Twice the signed UV area of each face, (u, v) taken as plain x, y."""
    t = m.uvs.astype(np.float64)[m.faces]
    a, b = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    return a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]


def _assert_same(got: Mesh, want: Mesh) -> None:
    """Positions, faces and UVs bit for bit; normals up to Mitsuba's re-normalisation."""
    np.testing.assert_array_equal(got.vertices, want.vertices)
    np.testing.assert_array_equal(got.faces, want.faces)
    np.testing.assert_array_equal(got.uvs, want.uvs)
    np.testing.assert_allclose(got.normals, want.normals, atol=1e-6)


def _components(m: Mesh, tol: float = 1e-6) -> list[np.ndarray]:
    """Face index sets of the parts, vertices at the same position welded."""
    pairs = cKDTree(m.vertices.astype(np.float64)).query_pairs(tol, output_type="ndarray")
    f = m.faces
    rows = np.concatenate([f[:, 0], f[:, 1], pairs[:, 0]])
    cols = np.concatenate([f[:, 1], f[:, 2], pairs[:, 1]])
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(m.n_vertices,) * 2)
    _, label = connected_components(graph, directed=False)
    face_label = label[f[:, 0]]
    return [np.flatnonzero(face_label == k) for k in np.unique(face_label)]


def _coverage(m: Mesh, res: int = 256, eps: float = 1e-6) -> np.ndarray:
    """How many UV triangles strictly contain each texel centre of a res × res grid."""
    count = np.zeros((res, res), dtype=np.int32)
    for tri in m.uvs.astype(np.float64)[m.faces] * res - 0.5:  # texel-centre coordinates
        lo = np.maximum(np.floor(tri.min(0)).astype(int), 0)
        hi = np.minimum(np.ceil(tri.max(0)).astype(int), res - 1)
        x, y = np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1))
        (x0, y0), (x1, y1), (x2, y2) = tri
        det = (y1 - y2) * (x0 - x2) + (x2 - x1) * (y0 - y2)
        l0 = ((y1 - y2) * (x - x2) + (x2 - x1) * (y - y2)) / det
        l1 = ((y2 - y0) * (x - x2) + (x0 - x2) * (y - y2)) / det
        inside = (l0 > eps) & (l1 > eps) & (1 - l0 - l1 > eps)
        count[y[inside], x[inside]] += 1
    return count


# --- built-ins ----------------------------------------------------------------------------------

def test_builtin_arrays(built: tuple[str, Mesh]) -> None:
    name, m = built
    assert m.vertices.dtype == np.float32 and m.vertices.shape == (m.n_vertices, 3)
    assert m.faces.dtype == np.int32 and m.faces.min() >= 0 and m.faces.max() < m.n_vertices
    assert m.uvs.dtype == np.float32 and np.isfinite(m.uvs).all()
    assert m.uvs.min() >= 0.0 and m.uvs.max() <= 1.0
    assert m.normals is not None and np.allclose(np.linalg.norm(m.normals, axis=1), 1, atol=1e-5)
    assert len(np.unique(m.faces)) == m.n_vertices, f"{name}: unreferenced vertices"
    assert (30 if name in PARTS else 100) <= m.n_faces <= 3000, f"{name}: {m.n_faces} triangles"


def test_builtin_no_degenerate_triangles(built: tuple[str, Mesh]) -> None:
    _, m = built
    assert m.face_areas().min() > 1e-7
    assert np.abs(_uv_cross(m)).min() > 1e-9


def test_builtin_parts_closed_and_outward(built: tuple[str, Mesh]) -> None:
    name, m = built
    v = m.vertices.astype(np.float64)
    cross = np.cross(v[m.faces[:, 1]] - v[m.faces[:, 0]], v[m.faces[:, 2]] - v[m.faces[:, 0]])
    parts = _components(m)
    assert len(parts) >= 1
    for faces in parts:
        c = cross[faces]
        closure = np.linalg.norm(c.sum(0)) / np.linalg.norm(c, axis=1).sum()
        assert closure < 1e-6, f"{name}: a part is not closed (or has a flipped piece): {closure:.2e}"
        volume = np.einsum("ij,ij->i", v[m.faces[faces, 0]], c).sum() / 6.0
        assert volume > 1e-6, f"{name}: a part has inward faces (volume {volume:.3g} m³)"


def test_builtin_normals_agree_with_winding(built: tuple[str, Mesh]) -> None:
    _, m = built
    fn = m.face_normals()
    for k in range(3):
        assert (np.einsum("ij,ij->i", fn, m.normals[m.faces[:, k]]) > 0.2).all()


def test_builtin_uvs_not_mirrored(built: tuple[str, Mesh]) -> None:
    # Seen from outside, every chart keeps u to the right and v down: in (u, v) taken as plain
    # x, y that is a clockwise (negative) UV winding for every counter-clockwise face.
    _, m = built
    assert (_uv_cross(m) < 0).all()


@pytest.mark.parametrize("name", NAMES)
def test_builtin_bounds(name: str) -> None:
    lo, hi = builtin_mesh(name).bounds()
    want_lo, want_hi = BOUNDS[name]
    np.testing.assert_allclose(lo, want_lo, atol=1e-3)
    np.testing.assert_allclose(hi, want_hi, atol=1e-3)
    assert abs(lo[1] - PARTS.get(name, 0.0)) < 1e-6  # stands on y = 0 (the sign's plate hangs)
    assert np.all(np.abs((lo + hi)[[0, 2]] / 2) < 0.05)  # centred on x = z = 0


def test_builtin_nominal_sizes() -> None:
    size = {n: np.subtract(*builtin_mesh(n).bounds()[::-1]) for n in NAMES}
    np.testing.assert_allclose(size["car"], (1.8, 1.5, 4.2), rtol=0.05)
    np.testing.assert_allclose(size["trash_bin"], (0.6, 1.0, 0.6), rtol=0.05)
    np.testing.assert_allclose(size["umbrella"][[0, 2]], (2.0, 2.0), rtol=0.05)
    assert size["traffic_cone"][1] == pytest.approx(0.7, rel=0.02)
    assert size["stop_sign"][0] == pytest.approx(0.75, rel=0.02)


def test_builtin_uv_charts_do_not_overlap(built: tuple[str, Mesh]) -> None:
    name, m = built
    count = _coverage(m)
    assert count.max() <= 1, f"{name}: {(count > 1).sum()} texels covered twice"
    assert (count > 0).mean() > (0.05 if name in PARTS else 0.2)  # the rasteriser did see the charts


def test_coverage_detects_overlap() -> None:
    m = builtin_mesh("trash_bin")
    assert _coverage(concat_meshes([m, m])).max() == 2


def test_builtin_main_surface_has_largest_share(built: tuple[str, Mesh]) -> None:
    name, m = built
    c = m.vertices.astype(np.float64)[m.faces].mean(1)
    main = MAIN[name](c, m.face_normals())
    uv_area = np.abs(_uv_cross(m)) / 2
    assert uv_area[main].sum() > 0.4 * uv_area.sum(), name
    density = uv_area / m.face_areas()  # UV area per m²
    if (~main).any():
        assert np.median(density[main]) > np.median(density[~main])


def test_stop_sign_face_looks_towards_plus_z_upright() -> None:
    m = builtin_mesh("stop_sign")
    c = m.vertices.astype(np.float64)[m.faces].mean(1)
    face = MAIN["stop_sign"](c, m.face_normals())
    vi = np.unique(m.faces[face])
    y, v = m.vertices[vi, 1], m.uvs[vi, 1]
    assert np.corrcoef(y, v)[0, 1] < -0.99  # top of the sign = top rows of the texture (small v)
    x, u = m.vertices[vi, 0], m.uvs[vi, 0]
    assert np.corrcoef(x, u)[0, 1] > 0.99  # seen from +Z, +X is on the right


def test_primitives_box_and_cylinder() -> None:
    b = box((1.0, 2.0, 3.0), (0.0, 1.0, 0.0))
    np.testing.assert_allclose(b.bounds()[0], (-0.5, 0.0, -1.5), atol=1e-6)
    np.testing.assert_allclose(b.bounds()[1], (0.5, 2.0, 1.5), atol=1e-6)
    assert b.surface_area() == pytest.approx(2 * (2 + 3 + 6), rel=1e-6)
    c = cylinder(0.2, 3.0, (1.0, 1.5, 0.0), segments=16)
    np.testing.assert_allclose(c.bounds()[0], (0.8, 0.0, -0.2), atol=1e-6)
    np.testing.assert_allclose(c.bounds()[1], (1.2, 3.0, 0.2), atol=1e-6)
    for m in (b, c):
        assert (_uv_cross(m) < 0).all() and _coverage(m).max() <= 1
        assert m.uvs.min() >= 0 and m.uvs.max() <= 1


def test_unknown_builtin() -> None:
    with pytest.raises(AssetError, match=r"unknown builtin asset 'xyz' \(valid: car, pedestrian, sign_pole, sphere, stop_sign, stop_sign_plate, "):
        builtin_mesh("xyz")


# --- PLY ----------------------------------------------------------------------------------------

def test_ply_round_trip_exact(built: tuple[str, Mesh], tmp_path: Path) -> None:
    name, m = built
    path = write_ply(m, tmp_path / f"{name}.ply")
    assert read_ply(path) == m
    header = path.read_bytes().split(b"end_header\n")[0].decode()
    assert "property float s\nproperty float t\n" in header  # Mitsuba's names for UVs
    assert "format binary_little_endian 1.0" in header


def test_read_ply_reads_u_v_names_too(tmp_path: Path) -> None:
    m = builtin_mesh("sphere")
    path = write_ply(m, tmp_path / "st.ply")
    uv = path.read_bytes().replace(b"property float s\nproperty float t\n",
                                   b"property float u\nproperty float v\n", 1)
    (tmp_path / "uv.ply").write_bytes(uv)
    assert read_ply(tmp_path / "uv.ply") == m


def test_ply_round_trip_without_normals(tmp_path: Path) -> None:
    m = builtin_mesh("sphere")
    bare = Mesh(m.vertices, m.faces, m.uvs)
    back = read_ply(write_ply(bare, tmp_path / "bare.ply"))
    assert back == bare and back.normals is None


def test_mitsuba_reads_written_ply(built: tuple[str, Mesh], tmp_path: Path, mi) -> None:  # noqa: ANN001
    name, m = built
    shape = mi.load_dict({"type": "ply", "filename": str(write_ply(m, tmp_path / f"{name}.ply"))})
    assert shape.has_vertex_texcoords() and shape.has_vertex_normals()
    np.testing.assert_array_equal(np.array(shape.vertex_positions_buffer()).reshape(-1, 3), m.vertices)
    np.testing.assert_array_equal(np.array(shape.faces_buffer()).reshape(-1, 3), m.faces)
    np.testing.assert_array_equal(np.array(shape.vertex_texcoords_buffer()).reshape(-1, 2), m.uvs)
    np.testing.assert_allclose(np.array(shape.vertex_normals_buffer()).reshape(-1, 3), m.normals, atol=1e-6)
    _assert_same(load_mesh_file(tmp_path / f"{name}.ply"), m)


def test_uv_to_texel_matches_mitsuba_bitmap(mi) -> None:  # noqa: ANN001
    import drjit as dr

    h, w = 4, 8
    rows, cols = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    data = np.stack([rows, cols, np.zeros_like(rows)], -1).astype(np.float32)
    tex = mi.load_dict({"type": "bitmap", "data": mi.TensorXf(data), "raw": True, "filter_type": "nearest"})
    uv = np.array([[0.01, 0.01], [0.01, 0.99], [0.99, 0.01], [0.3, 0.6], [0.9, 0.2]])
    si = dr.zeros(mi.SurfaceInteraction3f, len(uv))
    si.uv = mi.Point2f(uv[:, 0], uv[:, 1])
    got = np.array(tex.eval(si))  # channels first: (3, N)
    assert got.shape == (3, len(uv))
    got = got.T
    np.testing.assert_array_equal(got[:, :2], np.rint(uv_to_texel(uv, h, w)))


# --- users' files -------------------------------------------------------------------------------

OBJ_QUAD = """v -1 0 0\nv 1 0 0\nv 1 2 0\nv -1 2 0\n{vt}f {f1}\nf {f2}\n"""


def _write_obj(path: Path, with_uv: bool) -> Path:
    vt = "vt 0 0\nvt 1 0\nvt 1 0.25\nvt 0 0.25\n" if with_uv else ""
    f1, f2 = ("1/1 2/2 3/3", "1/1 3/3 4/4") if with_uv else ("1 2 3", "1 3 4")
    path.write_text(OBJ_QUAD.format(vt=vt, f1=f1, f2=f2))
    return path


def test_load_obj_with_uvs(tmp_path: Path, mi) -> None:  # noqa: ANN001
    m = load_mesh_file(_write_obj(tmp_path / "quad.obj", True))
    assert m.n_faces == 2 and m.n_vertices == 4
    order = np.lexsort(m.vertices.T[::-1])
    assert sorted(map(tuple, m.vertices.tolist())) == [(-1, 0, 0), (-1, 2, 0), (1, 0, 0), (1, 2, 0)]
    # Mitsuba flips OBJ's v (v up) into its own convention (v down): vt 0.25 → 0.75.
    by_pos = {tuple(p): tuple(uv) for p, uv in zip(m.vertices[order].tolist(), m.uvs[order].tolist())}
    assert by_pos[(-1.0, 0.0, 0.0)] == (0.0, 1.0)
    assert by_pos[(1.0, 2.0, 0.0)] == (1.0, 0.75)
    assert np.allclose(m.face_normals(), [0, 0, 1])


def test_load_obj_without_uvs(tmp_path: Path, mi) -> None:  # noqa: ANN001
    path = _write_obj(tmp_path / "bare.obj", False)
    with pytest.raises(AssetError) as err:
        load_mesh_file(path)
    msg = str(err.value)
    assert msg == (f"{path}: mesh has no UV coordinates (texcoords); undream needs a UV-mapped "
                   "mesh to place the adversarial texture")
    assert "\n" not in msg


def test_load_unparseable_file(tmp_path: Path, mi) -> None:  # noqa: ANN001
    path = tmp_path / "broken.obj"
    path.write_text("v 0 0\nf 1 2 3\n")
    with pytest.raises(AssetError) as err:
        load_mesh_file(path)
    msg = str(err.value)
    assert msg.startswith(f"{path}: Mitsuba cannot load this mesh: ") and "v 0 0" in msg
    assert "\n" not in msg and "parser.cpp" not in msg
    bad_ply = tmp_path / "broken.ply"
    bad_ply.write_text("garbage\n")
    with pytest.raises(AssetError, match=r"broken\.ply: Mitsuba cannot load this mesh: .*garbage"):
        load_mesh_file(bad_ply)


def test_load_missing_and_unsupported(tmp_path: Path) -> None:
    with pytest.raises(AssetError, match=r"nope\.obj: file not found$"):
        load_mesh_file(tmp_path / "nope.obj")
    (tmp_path / "mesh.stl").write_text("solid x\n")
    with pytest.raises(AssetError, match=r"unsupported mesh extension '\.stl' \(valid: \.obj, \.ply\)"):
        load_mesh_file(tmp_path / "mesh.stl")
    with pytest.raises(AssetError, match="file not found"):
        read_ply(tmp_path / "nope.ply")


def test_asset_mesh_builtin_scaled_and_relative_file(tmp_path: Path, mi) -> None:  # noqa: ANN001
    m = asset_mesh(Asset(name="bin", mesh="builtin:trash_bin", scale=2.0))
    np.testing.assert_allclose(m.bounds()[1][1], 2.0, atol=1e-5)
    write_ply(builtin_mesh("sphere"), tmp_path / "ball.ply")
    got = asset_mesh(Asset(name="ball", mesh="ball.ply", scale=0.5), base_dir=tmp_path)
    _assert_same(got, builtin_mesh("sphere").scaled(0.5))
    with pytest.raises(AssetError, match="file not found"):
        asset_mesh(Asset(name="ball", mesh="ball.ply"), base_dir=tmp_path / "elsewhere")


# --- the Mesh container -------------------------------------------------------------------------

def test_mesh_validation_names_the_field() -> None:
    v, f, uv = np.zeros((3, 3)), np.array([[0, 1, 2]]), np.zeros((3, 2))
    with pytest.raises(AssetError, match=r"^vertices: expected shape \(n, 3\)"):
        Mesh(np.zeros((3, 2)), f, uv)
    with pytest.raises(AssetError, match=r"^faces: vertex indices must be in \[0, 3\)"):
        Mesh(v, np.array([[0, 1, 3]]), uv)
    with pytest.raises(AssetError, match=r"^faces: must be integer"):
        Mesh(v, f.astype(float), uv)
    with pytest.raises(AssetError, match=r"^uvs: contains NaN"):
        Mesh(v, f, np.full((3, 2), np.nan))
    with pytest.raises(AssetError, match=r"^uvs: expected one UV per vertex"):
        Mesh(v, f, np.zeros((2, 2)))
    with pytest.raises(AssetError, match=r"^normals: expected one normal per vertex"):
        Mesh(v, f, uv, np.zeros((2, 3)))
    with pytest.raises(AssetError, match=r"^scale: must be a finite number > 0"):
        Mesh(v, f, uv).scaled(0.0)


def test_mesh_helpers() -> None:
    m = builtin_mesh("sphere")
    assert m.surface_area() == pytest.approx(np.pi, rel=0.01)  # 4π r², r = 0.5
    s = m.scaled(2.0)
    np.testing.assert_allclose(s.bounds()[1], (1.0, 2.0, 1.0), atol=1e-6)
    assert not m.vertices.flags.writeable
    np.testing.assert_allclose(uv_to_texel(np.array([0.0, 1.0]), 4, 8), (3.5, -0.5))


def test_no_mitsuba_at_import() -> None:
    code = ("import sys, undream.scene.mesh, undream.scene.builtin; "
            "sys.exit('mitsuba' in sys.modules or 'drjit' in sys.modules)")
    assert subprocess.run([sys.executable, "-c", code], cwd=Path(__file__).parents[1]).returncode == 0
