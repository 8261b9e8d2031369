"""OBJ reading (``geometry/meshio.py``): the bulk parser and the line parser agree on every file the bulk
parser takes, and every file it declines is read (or refused) line by line; the mesh checks that replaced
``np.unique(axis=0)`` give numpy's answer."""

import numpy as np
import pytest

from translucency_addon.errors import MeshError
from translucency_addon.geometry import meshio, primitives

QUAD = ["v 0 0 0", "v 1 0 0", "v 1 1 0", "v 0 1 0", "v 0.5 0.5 1"]


@pytest.mark.parametrize("faces, bulk", [
    (["f 1 2 5", "f 2 3 5", "f 3 4 5", "f 4 1 5", "f 1 3 2", "f 1 4 3"], True),
    (["f 1/1/1 2/2/2 5/5/5", "f 2//2 3//3 5//5", "f 3/3 4/4 5/5", "f 4 1 5", "f 1 3 2", "f 1 4 3"], True),
    (["f 1 2 5", "f 2 3 5", "f 3 4 5", "f 4 1 5", "f 1 4 3 2"], False),  # a quad: fanned
    (["f -5 -4 -1", "f 2 3 5", "f 3 4 5", "f 4 1 5", "f 1 3 2", "f 1 4 3"], False),  # negative indices
])
def test_bulk_parser_agrees_with_the_line_parser(tmp_path, faces, bulk):
    lines = QUAD + ["vn 0 0 1", "# comment", "o name", "s off"] + faces
    assert (meshio._parse_obj_bulk(lines) is not None) == bulk
    path = tmp_path / "m.obj"
    path.write_text("\n".join(lines) + "\n")
    V, F = meshio.load_obj(path)
    Vl, Fl = meshio._parse_obj_lines(path, lines)
    np.testing.assert_array_equal(V, np.asarray(Vl))
    np.testing.assert_array_equal(F, np.asarray(Fl))
    assert len(F) == 6


def test_extra_vertex_columns_and_bad_tokens_go_line_by_line(tmp_path):
    coloured = ["v 0 0 0 1 0 0", "v 1 0 0 1 0 0", "v 0 1 0 1 0 0", "v 0 0 1 1 0 0", "f 1 2 3"]
    assert meshio._parse_obj_bulk(coloured) is None
    (tmp_path / "c.obj").write_text("\n".join(coloured))
    np.testing.assert_array_equal(meshio.load_obj(tmp_path / "c.obj")[0][3], [0, 0, 1])
    (tmp_path / "bad.obj").write_text("v 0 0 x\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(MeshError, match="malformed vertex line 'v 0 0 x'"):
        meshio.load_obj(tmp_path / "bad.obj")


def test_saved_mesh_reads_back_in_bulk(tmp_path):
    V, F = primitives.icosphere(1.0, 2)
    meshio.save_obj(tmp_path / "s.obj", V, F)
    assert meshio._parse_obj_bulk((tmp_path / "s.obj").read_text().splitlines()) is not None
    V2, F2 = meshio.load_obj(tmp_path / "s.obj")
    np.testing.assert_allclose(V2, V, rtol=1e-8)
    np.testing.assert_array_equal(F2, F)


def test_unique_rows_and_boundary_edges_are_numpys():
    rng = np.random.default_rng(3)
    key = rng.integers(-3, 4, (3000, 3))
    first, inverse = meshio.unique_rows(key)
    _, f_np, i_np = np.unique(key, axis=0, return_index=True, return_inverse=True)
    np.testing.assert_array_equal(first, f_np)
    np.testing.assert_array_equal(inverse, i_np.ravel())
    V, F = primitives.icosphere(1.0, 2)
    F = F[rng.permutation(len(F))[:-7]]
    e = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    u, c = np.unique(e, axis=0, return_counts=True)
    np.testing.assert_array_equal(meshio.boundary_edges(F), u[c == 1])
