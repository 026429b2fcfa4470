"""The OBJ reader: raw ``v`` order, any whitespace, and one clear error (file and line) per bad input."""

from __future__ import annotations

import numpy as np
import pytest

from unibody.io.obj import read_obj

CUBE = b"""# a quad cube, with uv seams: vt and v/vt/vn corners must not split vertices
mtllib cube.mtl
o cube
v -1 -1 -1
v 1 -1 -1
v 1 1 -1
v -1 1 -1
v -1 -1 1
v 1 -1 1
v 1 1 1
v -1 1 1
vt 0 0
vt 1 0
vt 1 1
vn 0 0 1
usemtl skin
f 1/1/1 2/2/1 3/3/1 4/1/1
f 5//1 8//1 7//1 6//1
f 1 5 6 2
f 2 6 7 3
f 3 7 8 4
f 5 1 4 8
"""


def _write(tmp_path, data: bytes, name: str = "mesh.obj"):
    path = tmp_path / name
    path.write_bytes(data)
    return path


def test_reads_raw_vertex_order_and_polygons(tmp_path):
    v, faces = read_obj(_write(tmp_path, CUBE))
    assert v.dtype == np.float64 and v.shape == (8, 3)
    assert np.array_equal(v[6], [1, 1, 1])
    assert faces[0] == [0, 1, 2, 3] and faces[1] == [4, 7, 6, 5] and len(faces) == 6


def test_any_whitespace_separates_fields(tmp_path):
    data = b"v\t0 0 0\nv  1\t0   0\r\nv\t0\t1\t0 1.0\nf\t1 2\t3\n"  # tabs, runs of spaces, CRLF, a w value
    v, faces = read_obj(_write(tmp_path, data))
    assert np.array_equal(v, [[0, 0, 0], [1, 0, 0], [0, 1, 0]]) and faces == [[0, 1, 2]]


def test_relative_indices_count_back_from_the_last_vertex(tmp_path):
    data = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf -3 -2 -1\nv 0 0 1\nf -1 1/1 -2\n"
    _, faces = read_obj(_write(tmp_path, data))
    assert faces == [[0, 1, 2], [3, 0, 2]]


def test_comments_and_names_in_any_encoding_are_skipped(tmp_path):
    data = b"# caf\xe9 (latin-1)\no cor\xe7o\ng \xff\xfe\nv 0 0 0 # d\xe9j\xe0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"
    v, faces = read_obj(_write(tmp_path, data))
    assert v.shape == (3, 3) and faces == [[0, 1, 2]]


TRI = b"v 0 0 0\nv 1 0 0\nv 0 1 0\n"


@pytest.mark.parametrize(
    ("data", "match"),
    [
        (
            TRI + b"f 1 2 99999999999999999999999\n",
            r"mesh\.obj:4: vertex index '99999999999999999999999' is out of range",
        ),
        (TRI + b"f 1 2 4\n", r"mesh\.obj: a face refers to vertex 4, but the file has 3 vertices"),
        (
            TRI + b"f 0 1 2\n",
            r"mesh\.obj:4: vertex index 0 is out of range \(3 vertices read so far; OBJ indices start",
        ),
        (TRI + b"f -4 1 2\n", r"mesh\.obj:4: vertex index -4 is out of range"),
        (TRI + b"f 1 2 x\n", r"mesh\.obj:4: face corner 'x' does not start with a vertex index"),
        (TRI + b"f 1 2 1_0\n", r"mesh\.obj:4: face corner '1_0' does not start"),
        (TRI + b"f 1 2 /3\n", r"mesh\.obj:4: face corner '/3' does not start"),
        (TRI + b"f 1 2\n", r"mesh\.obj:4: a face needs at least 3 vertices, got 2"),
        (b"v 0 0\n", r"mesh\.obj:1: a 'v' line needs 3 coordinates, got 2"),
        (b"v 0 0 abc\n", r"mesh\.obj:1: vertex coordinate 'abc' is not a number"),
        (b"v 0 0 1_0\n", r"mesh\.obj:1: vertex coordinate '1_0' is not a number"),
        (b"v 0 0 nan\n", r"mesh\.obj:1: vertex coordinate 'nan' is not finite"),
        (b"v 0 0 1e999\n", r"mesh\.obj:1: vertex coordinate '1e999' is not finite"),
        (b"v 0 0 -inf\n", r"mesh\.obj:1: vertex coordinate '-inf' is not finite"),
        (b"v 0 0 caf\xe9\n", r"mesh\.obj:1: vertex coordinate 'caf\\\\xe9' is not a number"),
        (b"# only a comment\nvt 0 0\n", r"mesh\.obj: no 'v' lines found"),
        (b"", r"mesh\.obj: no 'v' lines found"),
    ],
)
def test_bad_input_names_file_and_line(tmp_path, data, match):
    with pytest.raises(ValueError, match=match):
        read_obj(_write(tmp_path, data))


def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError):
        read_obj(tmp_path / "missing.obj")
