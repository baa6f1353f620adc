import numpy as np
import open3d as o3d
import pytest
import trimesh

from o3dsoft.errors import InputError, UsageError
from o3dsoft.io import (
    LAS_RESOLUTION,
    read_attributes,
    read_points,
    read_poses,
    read_scans,
    read_transform,
    sample_mesh,
    write_moved,
    write_points,
    write_transform,
)
from o3dsoft.transforms import apply_transform, euler_to_matrix, rigid

from .conftest import blob, python_output


@pytest.fixture
def pts():
    return blob(np.random.default_rng(0), 200)


@pytest.mark.parametrize("ext", [".ply", ".pcd", ".xyz", ".xyzn", ".pts", ".csv", ".npy", ".las"])
def test_point_formats_round_trip(tmp_path, pts, ext):
    path = write_points(tmp_path / f"cloud{ext}", pts)
    back = read_points(path)
    assert back.shape == pts.shape
    assert np.allclose(back, pts, atol=LAS_RESOLUTION / 2 if ext == ".las" else 1e-5)  # LAS stores integers
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary left


@pytest.mark.parametrize("ext", [".off", ".stl", ".obj", ".ply"])
def test_meshes_are_sampled_on_faces(tmp_path, ext):
    box = trimesh.creation.box(extents=(2.0, 1.0, 0.5))
    path = tmp_path / f"box{ext}"
    box.export(path)
    points = read_points(path, mesh_points=3000)
    assert points.shape == (3000, 3)
    # Every sample lies on the box's surface: on one of its faces, inside the others' bounds.
    half = np.array([1.0, 0.5, 0.25])
    assert (np.abs(points) <= half + 1e-6).all()
    assert np.isclose(np.abs(points) / half, 1.0, atol=1e-5).any(axis=1).all()
    # Uniform over area: the two 2 x 1 faces hold 4 of the 7 units of area, so ~4 / 7 of the points.
    share = np.isclose(np.abs(points[:, 2]), 0.25, atol=1e-6).mean()
    assert share == pytest.approx(4 / 7, abs=0.04)
    assert np.array_equal(points, read_points(path, mesh_points=3000))  # deterministic


def test_a_mesh_vertex_with_no_finite_coordinates_leaves_out_its_faces_only(tmp_path):
    box = trimesh.creation.box(extents=(2.0, 1.0, 0.5))
    vertices = np.array(box.vertices)
    vertices[0] = np.nan  # one corner of eight: the faces around it go, the rest are sampled
    body = "".join(f"v {x} {y} {z}\n" for x, y, z in vertices) + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in box.faces)
    (tmp_path / "nan.obj").write_text(body)
    points = read_points(tmp_path / "nan.obj", mesh_points=2000)
    assert points.shape == (2000, 3) and np.isfinite(points).all()  # it had read 2,000 NaN rows
    assert (np.abs(points) <= [1.0 + 1e-6, 0.5 + 1e-6, 0.25 + 1e-6]).all()
    tri = "v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n"
    (tmp_path / "all.obj").write_text(tri)
    with pytest.raises(InputError, match="every face has a vertex with a non-finite coordinate \\(vertex 3, counting from 1\\)"):
        read_points(tmp_path / "all.obj")


def test_sample_mesh_seeded():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=float)
    f = np.array([[0, 1, 2]])
    a, b = sample_mesh(v, f, 100, seed=1), sample_mesh(v, f, 100, seed=2)
    assert not np.array_equal(a, b)
    assert (a[:, 2] == 0).all() and (a[:, 0] + a[:, 1] <= 1 + 1e-9).all()


def test_missing_file_and_unknown_extension(tmp_path):
    with pytest.raises(UsageError, match="no such file"):
        read_points(tmp_path / "nope.ply")
    (tmp_path / "cloud.abc").write_text("1 2 3\n")
    with pytest.raises(UsageError, match="unknown extension '.abc'"):
        read_points(tmp_path / "cloud.abc")


def test_empty_files(tmp_path):
    _refused(tmp_path / "empty.xyz", "", "empty.xyz: parsed to 0 points")
    _refused(tmp_path / "garbage.ply", "this is not a ply file\n", "garbage.ply: parsed to 0 points")


def _refused(path, text, match):
    """Write `text` to `path` and check that reading it raises an InputError matching `match`."""
    path.write_text(text)
    with pytest.raises(InputError, match=match):
        read_points(path)


def test_text_clouds_name_the_first_line_they_cannot_read(tmp_path, pts):
    rows = ["%.6f %.6f %.6f" % tuple(p) for p in pts]
    (tmp_path / "commas.xyz").write_text("\n".join(r.replace(" ", ",") for r in rows) + "\n")
    with pytest.raises(InputError, match=r"commas.xyz: parsed to 0 points; .* Line 1: .*; expected 3 numbers separated by spaces \(200 lines not read\)"):
        read_points(tmp_path / "commas.xyz")
    # Open3D skips a line it cannot parse: the cloud would be read in part.
    (tmp_path / "one_bad.xyz").write_text("\n".join(rows[:50] + ["1.0, 2.0, 3.0"] + rows[50:]) + "\n")
    with pytest.raises(InputError, match=r"one_bad.xyz: 200 points read, but not every line. Line 51: '1.0, 2.0, 3.0'; .* \(1 line not read\)"):
        read_points(tmp_path / "one_bad.xyz")
    (tmp_path / "quoted.xyz").write_text("\n".join(rows[:3] + ['"1" "2" "3"']) + "\n")  # Open3D skips quoted numbers
    with pytest.raises(InputError, match="quoted.xyz: 3 points read, but not every line. Line 4: "):
        read_points(tmp_path / "quoted.xyz")
    (tmp_path / "short.xyzn").write_text("\n".join(r + " 0 0 1" for r in rows[:10]) + "\n1 2 3\n")
    with pytest.raises(InputError, match=r"short.xyzn: 10 points read, .* Line 11: '1 2 3'; expected 6 numbers"):
        read_points(tmp_path / "short.xyzn")
    # A header before the numbers (CloudCompare's, or .pts's count) is no bad line; blank lines neither.
    (tmp_path / "header.xyz").write_text("// exported\nX Y Z\n" + "\n\n".join(rows) + "\n")
    assert np.allclose(read_points(tmp_path / "header.xyz"), pts, atol=1e-6)
    (tmp_path / "count.pts").write_text("200\n" + "\n".join(rows) + "\n")
    assert len(read_points(tmp_path / "count.pts")) == 200


def test_delimited_text_exports_are_read_by_their_named_columns(tmp_path, pts):
    rows = [f"{x},{y},{z},200,10,10" for x, y, z in pts]  # CloudCompare's .txt export
    (tmp_path / "cc.txt").write_text("//X,Y,Z,R,G,B\n" + "\n".join(rows) + "\n")
    assert np.allclose(read_points(tmp_path / "cc.txt"), pts)
    rows = [f'{i};"{z}";{y};{x}' for i, (x, y, z) in enumerate(pts)]  # columns in another order
    (tmp_path / "named.csv").write_text('id;"Z";"Y";"X"\n' + "\n\n".join(rows) + "\n")
    assert np.allclose(read_points(tmp_path / "named.csv"), pts)
    (tmp_path / "tabs.txt").write_text("\n".join("\t".join(map(str, p)) for p in pts) + "\n")
    assert np.allclose(read_points(tmp_path / "tabs.txt"), pts)
    _refused(tmp_path / "short.csv", "X,Y,Z\n1,2,3\n4,5\n", "short.csv: line 3: '4,5'; expected its columns x, y, z separated by commas, as on line 2")
    (tmp_path / "decimal_commas.csv").write_text("X;Y;Z\n1,5;2,5;3,5\n-4;5,25;6\n")  # a spreadsheet's export in many locales
    np.testing.assert_array_equal(read_points(tmp_path / "decimal_commas.csv"), [[1.5, 2.5, 3.5], [-4.0, 5.25, 6.0]])
    _refused(tmp_path / "words.csv", "a,b,c\nd,e,f\n", "words.csv: no line of at least 3 numbers separated by commas, semicolons, tabs or spaces")


def test_a_ply_without_y_or_z_is_refused(tmp_path, pts):
    # Open3D reads such vertices with whatever memory held for the missing coordinates.
    (tmp_path / "x_only.ply").write_text("ply\nformat ascii 1.0\nelement vertex 40\nproperty float x\nend_header\n" + "1\n" * 40)
    with pytest.raises(InputError, match=r"x_only.ply: its vertices have no y, z property \(the header names x\); expected x, y and z"):
        read_points(tmp_path / "x_only.ply")
    header = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nproperty uchar red\n"
    (tmp_path / "mesh.ply").write_text(header + "element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0 1\n1 0 0 2\n0 1 0 3\n3 0 1 2\n")
    assert len(read_points(tmp_path / "mesh.ply", mesh_points=50)) == 50  # a face's list property is no coordinate
    write_points(tmp_path / "written.ply", pts)
    assert np.allclose(read_points(tmp_path / "written.ply"), pts)


def _ply(path, columns, types, form="binary_little_endian", faces=None):
    """Write a PLY whose vertices hold `columns` (name -> (N,) values) in that order, of `types`."""
    n = len(next(iter(columns.values())))
    header = f"ply\nformat {form} 1.0\nelement vertex {n}\n" + "".join(f"property {types[c]} {c}\n" for c in columns)
    if faces is not None:
        header += f"element face {len(faces)}\nproperty list uchar int vertex_indices\n"
    header += "end_header\n"
    codes = {"float": "f4", "double": "f8", "uchar": "u1", "ushort": "u2"}
    with open(path, "wb") as f:
        f.write(header.encode())
        if form == "ascii":
            for row in zip(*columns.values()):
                f.write((" ".join(repr(float(v)) if types[c] in ("float", "double") else str(int(v)) for c, v in zip(columns, row)) + "\n").encode())
            for face in faces if faces is not None else []:
                f.write(("3 " + " ".join(map(str, face)) + "\n").encode())
        else:
            order = ">" if "big" in form else "<"
            record = np.empty(n, dtype=[(c, order + codes[types[c]]) for c in columns])
            for c, values in columns.items():
                record[c] = values
            f.write(record.tobytes())
            for face in faces if faces is not None else []:
                f.write(np.uint8(3).tobytes() + np.asarray(face, dtype=order + "i4").tobytes())


@pytest.mark.parametrize("form", ["binary_little_endian", "binary_big_endian", "ascii"])
def test_a_ply_in_any_property_order_is_read_as_written(tmp_path, pts, form):
    # Open3D's reader moves to the next point at z (nz, blue): a file storing z before x or y had
    # its points mixed up, silently.
    rng = np.random.default_rng(1)
    rgb, normals = rng.integers(0, 256, (len(pts), 3)), rng.normal(size=(len(pts), 3))
    values = {"intensity": rng.uniform(size=len(pts)), "z": pts[:, 2], "blue": rgb[:, 2], "x": pts[:, 0], "nz": normals[:, 2]}
    values.update({"green": rgb[:, 1], "y": pts[:, 1], "red": rgb[:, 0], "nx": normals[:, 0], "ny": normals[:, 1]})
    types = dict.fromkeys(values, "float") | {"red": "uchar", "green": "uchar", "blue": "uchar"}
    _ply(tmp_path / "any_order.ply", values, types, form)
    got = read_points(tmp_path / "any_order.ply")
    assert np.allclose(got, pts, atol=1e-6)
    attributes = read_attributes(tmp_path / "any_order.ply", len(got))
    assert np.allclose(attributes.colors, rgb / 255) and np.allclose(attributes.normals, normals, atol=1e-6)
    # A mesh in that order is sampled on the faces it holds.
    corners = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    _ply(tmp_path / "mesh.ply", {"z": corners[:, 2], "x": corners[:, 0], "y": corners[:, 1]}, dict.fromkeys("xyz", "float"), form, faces=[(0, 1, 2)])
    sampled = read_points(tmp_path / "mesh.ply", mesh_points=100)
    assert len(sampled) == 100 and np.allclose(sampled[:, 2], 0) and (sampled[:, :2].sum(axis=1) <= 1 + 1e-9).all()


@pytest.mark.parametrize("scale", [1.0, 255.0])
def test_float_colours_are_read_in_their_range(tmp_path, pts, scale):
    # Open3D divides every PLY colour by 255: floats in 0-1 came out nearly black.
    rgb = np.random.default_rng(2).uniform(size=(len(pts), 3))
    columns = {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2], "red": rgb[:, 0] * scale, "green": rgb[:, 1] * scale, "blue": rgb[:, 2] * scale}
    _ply(tmp_path / "float_colours.ply", columns, dict.fromkeys(columns, "float"))
    assert np.allclose(read_attributes(tmp_path / "float_colours.ply", len(pts)).colors, rgb, atol=1e-6)


@pytest.mark.parametrize("ext, ascii", [(".ply", False), (".ply", True), (".pcd", False), (".pcd", True)])
def test_a_file_cut_short_is_refused(tmp_path, pts, ext, ascii):
    # Open3D reads the missing points of a cut PLY, and of a cut ascii PCD, as zeros.
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    o3d.io.write_point_cloud(str(tmp_path / f"whole{ext}"), cloud, write_ascii=ascii)
    assert np.allclose(read_points(tmp_path / f"whole{ext}"), pts, atol=1e-5)
    data = (tmp_path / f"whole{ext}").read_bytes()
    header = data.index(b"end_header\n" if ext == ".ply" else b"DATA") + 16
    (tmp_path / f"cut{ext}").write_bytes(data[: header + (len(data) - header) // 2])
    noun = "vertices" if ext == ".ply" else "points"
    with pytest.raises(InputError, match=rf"cut{ext}: the header declares 200 {noun}, but the file ends after (9[0-9]|10[0-9]); is it complete"):
        read_points(tmp_path / f"cut{ext}")


@pytest.mark.parametrize("ext", [".ply", ".pcd"])
def test_an_ascii_point_line_short_of_a_value_is_refused(tmp_path, pts, ext):
    # Open3D fills such a PCD point from uninitialised memory, and reads a PLY's values after it shifted.
    import open3d as o3d

    o3d.io.write_point_cloud(str(tmp_path / f"whole{ext}"), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)), write_ascii=True)
    lines = (tmp_path / f"whole{ext}").read_text().splitlines()
    first = next(i for i, line in enumerate(lines) if line.startswith(("end_header", "DATA"))) + 1
    assert np.allclose(read_points(tmp_path / f"whole{ext}"), pts, atol=1e-5)
    short = lines[: first + 100] + [" ".join(lines[first + 100].split()[:2])] + lines[first + 101 :]
    (tmp_path / f"short{ext}").write_text("\n".join(short) + "\n")
    with pytest.raises(InputError, match=rf"short{ext}: line {first + 101}: '[-0-9. e]+' holds 2 values; the header's (vertices|points) hold 3 each"):
        read_points(tmp_path / f"short{ext}")
    (tmp_path / f"last{ext}").write_text("\n".join(lines[:-1] + [" ".join(lines[-1].split()[:2])]))  # cut inside the last point
    with pytest.raises(InputError, match=rf"last{ext}: the header declares 200 (vertices|points), but the file ends after 199"):
        read_points(tmp_path / f"last{ext}")
    blank = lines[: first + 100] + [""] + lines[first + 100 :]  # a blank line: Open3D skips it
    (tmp_path / f"blank{ext}").write_text("\n".join(blank) + "\n")
    assert np.allclose(read_points(tmp_path / f"blank{ext}"), pts, atol=1e-5)


def test_a_pts_file_cut_short_is_refused(tmp_path, pts):
    # Open3D reads the points a .pts count declares but its lines lack from uninitialised memory.
    rows = ["%.6f %.6f %.6f 0 10 20 30" % tuple(p) for p in pts]
    (tmp_path / "whole.pts").write_text("200\n" + "\n".join(rows) + "\n")
    assert np.allclose(read_points(tmp_path / "whole.pts"), pts, atol=1e-6)
    (tmp_path / "cut.pts").write_text("200\n" + "\n".join(rows[:99]) + "\n")
    with pytest.raises(InputError, match=r"cut.pts: the header declares 200 points, but the file ends after 99; is it complete"):
        read_points(tmp_path / "cut.pts")
    (tmp_path / "plus.pts").write_text("+200\n" + "\n".join(rows[:99]) + "\n")  # a count Open3D reads too
    with pytest.raises(InputError, match=r"plus.pts: the header declares 200 points, but the file ends after 99"):
        read_points(tmp_path / "plus.pts")
    (tmp_path / "mid.pts").write_text("200\n" + "\n".join(rows[:199]) + "\n" + rows[199][:12])  # cut inside the last point
    with pytest.raises(InputError, match=r"mid.pts: line 201: the file ends in the middle of a point; is it complete"):
        read_points(tmp_path / "mid.pts")
    (tmp_path / "gap.pts").write_text("200\n" + "\n".join(rows[:150]) + "\n\n" + "\n".join(rows[150:]) + "\n")  # Open3D reads the blank line as a point
    with pytest.raises(InputError, match=r"gap.pts: line 152: ''; expected x y z \(line 1 counts 200 points"):
        read_points(tmp_path / "gap.pts")
    (tmp_path / "nocount.pts").write_text("\n".join(rows) + "\n")  # Open3D reads the first x as the count
    with pytest.raises(InputError, match=r"nocount.pts: its first line .* is a point, not the point count"):
        read_points(tmp_path / "nocount.pts")


@pytest.mark.parametrize(
    "ext, share, match",
    [
        (".off", 0.3, "8 vertices, but the file ends after [0-7]"),
        (".off", 0.8, "12 faces, but the file ends after"),
        (".stl", 0.7, "12 triangles, but the file ends after 7"),
        (".ply", 0.8, "8 vertices, but the file ends after 7"),  # inside the last vertex's line
        (".ply", 0.95, "12 faces, but the file ends after"),
    ],
)
def test_a_mesh_cut_short_is_refused(tmp_path, ext, share, match):
    # Open3D samples the faces it read: a part of the surface, without a word.
    box = trimesh.creation.box(extents=(2.0, 1.0, 0.5))
    data = trimesh.exchange.ply.export_ply(box, encoding="ascii") if ext == ".ply" else box.export(file_type=ext[1:])
    data = data.encode() if isinstance(data, str) else data
    (tmp_path / f"cut{ext}").write_bytes(data[: int(len(data) * share)])
    with pytest.raises(InputError, match=f"cut{ext}: the header declares {match}"):
        read_points(tmp_path / f"cut{ext}")
    binary = trimesh.exchange.ply.export_ply(box, encoding="binary")
    header = binary.index(b"end_header\n") + 11
    (tmp_path / "cut.ply").write_bytes(binary[: header + 5 * 12])  # 5 of its 8 vertices (three float32 each)
    with pytest.raises(InputError, match="cut.ply: the header declares 8 vertices, but the file ends after 5"):
        read_points(tmp_path / "cut.ply")


@pytest.mark.parametrize("share, record", [(0.3, "v"), (0.9, "f")])
def test_an_obj_cut_in_a_record_or_with_a_short_one_is_refused(tmp_path, share, record):
    # OBJ declares no counts: a file cut in its vertices left a numpy error, one cut in its faces a part of the surface.
    text = trimesh.creation.icosphere(subdivisions=2).export(file_type="obj")
    cut = text[: int(len(text) * share)].rstrip("0123456789 -.\n") + " 1"  # one field short: the keyword and one number
    (tmp_path / "cut.obj").write_text(cut)
    line = cut.count("\n") + 1
    with pytest.raises(InputError, match=rf"cut.obj: line {line}: the file ends in the middle of a '{record}' record \(1 of its 3 fields\); is it complete"):
        read_points(tmp_path / "cut.obj")
    (tmp_path / "whole.obj").write_text(text.rstrip("\n"))  # no line end after the last record: whole
    assert np.allclose(np.linalg.norm(read_points(tmp_path / "whole.obj", mesh_points=100), axis=1), 1.0, atol=0.1)
    # A vertex line of two numbers mid-file: its readers skip it, and the faces after it join the wrong vertices.
    (tmp_path / "bad.obj").write_text("v 0 0 0\r\nv 1 0\r\nv 0 1 0\r\nv 0 0 1\r\nv 1 1 1\r\nf 1 2 3\r\n")
    with pytest.raises(InputError, match=r"bad.obj: line 2: a 'v' record with 2 field\(s\), expected at least 3; is the file damaged"):
        read_points(tmp_path / "bad.obj")
    (tmp_path / "bad.off").write_text("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 5\n")  # a face naming a sixth vertex of three
    with pytest.raises(InputError, match=r"bad.off: a face refers to vertex 6 \(counting from 1\), but 3 vertices were read"):
        read_points(tmp_path / "bad.off")


@pytest.mark.parametrize("source_ext", [".ply", ".pcd", ".xyzn"])
def test_a_moved_cloud_keeps_the_attributes_its_format_holds(tmp_path, source_ext):
    rng = np.random.default_rng(0)
    points, colors = rng.normal(size=(300, 3)), rng.random((300, 3))
    normals = rng.normal(size=(300, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    cloud.colors, cloud.normals = o3d.utility.Vector3dVector(colors), o3d.utility.Vector3dVector(normals)
    source = tmp_path / f"source{source_ext}"
    o3d.io.write_point_cloud(str(source), cloud)
    T = rigid(euler_to_matrix(np.array([10.0, -20.0, 30.0])), np.array([1.0, 2.0, 3.0]))
    read = read_points(source)
    carried = {".ply": (True, True), ".pcd": (True, True), ".xyzn": (False, True), ".csv": (False, False), ".npy": (False, False)}
    for out_ext, (has_colors, has_normals) in carried.items():
        out = write_moved(tmp_path / f"out{out_ext}", source, read, T)
        assert np.allclose(read_points(out), apply_transform(T, points), atol=1e-5)  # PCD holds float32
        if out_ext in (".csv", ".npy"):
            continue
        back = o3d.io.read_point_cloud(str(out))
        kept_colors = source_ext != ".xyzn" and has_colors  # .xyzn holds no colour to carry
        assert back.has_colors() == kept_colors and back.has_normals() == has_normals
        if kept_colors:
            assert np.abs(np.asarray(back.colors) - colors).max() <= 0.5 / 255 + 1e-6
        assert np.allclose(np.asarray(back.normals), normals @ T[:3, :3].T, atol=1e-6)
    mesh = trimesh.creation.box().export(file_type="ply")  # a mesh's points are sampled: nothing to carry
    (tmp_path / "mesh.ply").write_bytes(mesh)
    assert read_attributes(tmp_path / "mesh.ply", len(read_points(tmp_path / "mesh.ply"))) == (None, None)


def test_a_moved_las_keeps_every_dimension(tmp_path):
    laspy = pytest.importorskip("laspy")
    rng = np.random.default_rng(1)
    xyz = rng.normal(size=(200, 3)) * 10 + [500000.0, 4000000.0, 50.0]  # georeferenced, at a 1 cm step
    header = laspy.LasHeader(point_format=3, version="1.4")
    header.scales, header.offsets = np.full(3, 0.01), np.floor(xyz.min(axis=0))
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz.T
    las.intensity, las.classification = np.arange(200, dtype=np.uint16), np.full(200, 2, dtype=np.uint8)
    las.red = rng.integers(0, 65535, 200).astype(np.uint16)
    las.write(str(tmp_path / "scan.las"))
    read = read_points(tmp_path / "scan.las")
    T = rigid(euler_to_matrix(np.array([0.0, 0.0, 90.0])), np.array([10.0, 0.0, 0.0]))
    write_moved(tmp_path / "moved.las", tmp_path / "scan.las", read, T)
    moved = laspy.read(str(tmp_path / "moved.las"))
    assert moved.header.point_format.id == 3 and len(moved.points) == 200
    assert np.allclose(np.column_stack([moved.x, moved.y, moved.z]), apply_transform(T, read), atol=1e-4)
    for name in ("intensity", "classification", "red"):
        assert np.array_equal(np.asarray(moved[name]), np.asarray(las[name]))
    las.green, las.blue = las.red // 2, las.red // 4
    las.write(str(tmp_path / "scan.las"))  # coloured: its colours go into a PLY too, in 0-1
    write_moved(tmp_path / "moved.ply", tmp_path / "scan.las", read, T)
    coloured = o3d.io.read_point_cloud(str(tmp_path / "moved.ply"))
    rgb = np.column_stack([las.red, las.green, las.blue]) / 65535.0
    assert np.abs(np.asarray(coloured.colors) - rgb).max() <= 0.5 / 255 + 1e-6
    assert read_attributes(tmp_path / "scan.las", 199) == (None, None)  # not the points read: nothing
    # Stored at the finest step that holds it, a 100-unit cube turned 45 degrees needs a coarser one: taken, not refused.
    cube = rng.random((200, 3)) * 100.0
    header = laspy.LasHeader(point_format=0, version="1.4")
    header.scales, header.offsets = np.full(3, 100.0 / 2**31 * 1.01), np.zeros(3)
    fine = laspy.LasData(header)
    fine.x, fine.y, fine.z = cube.T
    fine.write(str(tmp_path / "fine.las"))
    turn = rigid(euler_to_matrix(np.array([0.0, 0.0, 45.0])), np.zeros(3))
    write_moved(tmp_path / "turned.las", tmp_path / "fine.las", read_points(tmp_path / "fine.las"), turn)
    turned = laspy.read(str(tmp_path / "turned.las"))
    assert np.allclose(np.column_stack([turned.x, turned.y, turned.z]), apply_transform(turn, read_points(tmp_path / "fine.las")), atol=1e-6)


def test_a_binary_ply_cut_in_its_faces_and_an_ascii_stl_cut_short_are_refused(tmp_path):
    box = trimesh.creation.box(extents=(2.0, 1.0, 0.5))
    binary = trimesh.exchange.ply.export_ply(box, encoding="binary")
    (tmp_path / "faces.ply").write_bytes(binary[:-20])  # all 8 vertices, the faces cut within the 11th
    with pytest.raises(InputError, match="faces.ply: the header declares 12 faces, but the file ends after 10; is it complete"):
        read_points(tmp_path / "faces.ply")
    text = box.export(file_type="stl_ascii")
    (tmp_path / "cut.stl").write_text(text[: int(len(text) * 0.95)])
    with pytest.raises(InputError, match="cut.stl: an ascii STL that ends before its closing 'endsolid' line; is it complete"):
        read_points(tmp_path / "cut.stl")
    # Whole files are read: ascii STLs (with a name in UTF-8, NUL bytes or a comment after the
    # end), a binary STL whose 80-byte header begins with "solid", a binary PLY of one quad.
    (tmp_path / "whole.stl").write_text(text)
    (tmp_path / "named.stl").write_bytes(text.replace("endsolid", "endsolid W\u00fcrfel").encode() + b"\0" * 16)
    (tmp_path / "comment.stl").write_bytes(text.encode() + b"; exported by a scanner\n")
    solid = box.export(file_type="stl")
    (tmp_path / "solid_header.stl").write_bytes(b"solid" + solid[5:])
    for name in ("whole.stl", "named.stl", "comment.stl", "solid_header.stl"):
        points = read_points(tmp_path / name, mesh_points=200)
        assert np.allclose(np.abs(points).max(axis=0), [1.0, 0.5, 0.25])
    header = b"ply\nformat binary_little_endian 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
    header += b"element face 1\nproperty list uchar int vertex_indices\nend_header\n"
    square = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype="<f4").tobytes() + bytes([4]) + np.arange(4, dtype="<i4").tobytes()
    (tmp_path / "quad.ply").write_bytes(header + square)
    points = read_points(tmp_path / "quad.ply", mesh_points=100)
    assert points.shape == (100, 3) and np.all(points[:, 2] == 0) and points[:, :2].min() >= 0 and points[:, :2].max() <= 1
    (tmp_path / "triangle.ply").write_bytes(header.replace(b"vertex 4", b"vertex 3") + square[:36] + bytes([3]) + np.arange(3, dtype="<i4").tobytes())
    assert len(read_points(tmp_path / "triangle.ply", mesh_points=10)) == 10  # 13 bytes: the least a face takes


def test_an_off_with_its_counts_on_the_keywords_line_is_read(tmp_path):
    # ModelNet40's known malformed header, which Open3D reads as a mesh without faces.
    (tmp_path / "modelnet.off").write_text("OFF4 1 0\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 1 2\n")
    points = read_points(tmp_path / "modelnet.off", mesh_points=100)
    assert points.shape == (100, 3) and np.all(points[:, 2] == 0) and np.all(points[:, :2].sum(axis=1) <= 1 + 1e-9)


def test_mesh_without_faces(tmp_path):
    (tmp_path / "nofaces.off").write_text("OFF\n3 0 0\n0 0 0\n1 0 0\n0 1 0\n")
    with pytest.raises(InputError, match="nofaces.off: mesh has 3 vertices but no faces"):
        read_points(tmp_path / "nofaces.off")


def test_bad_npy(tmp_path):
    np.save(tmp_path / "bad.npy", np.zeros((5, 2)))
    with pytest.raises(InputError, match=r"shape \(N, 3\)"):
        read_points(tmp_path / "bad.npy")
    (tmp_path / "corrupt.npy").write_bytes(b"\x93NUMPY garbage")
    with pytest.raises(InputError, match="not a readable .npy"):
        read_points(tmp_path / "corrupt.npy")


def test_transform_text_formats(tmp_path):
    T = np.eye(4)
    T[:3, 3] = [1, 2, 3]
    (tmp_path / "ws.txt").write_text("1 0 0 1\n0 1 0 2\n0 0 1 3\n0 0 0 1\n")
    (tmp_path / "comma.txt").write_text("# a comment\n1,0,0,1\n0,1,0,2\n0,0,1,3\n0,0,0,1\n")
    (tmp_path / "rt.txt").write_text("1 0 0 1\n0 1 0 2\n0 0 1 3\n")
    for name in ("ws.txt", "comma.txt", "rt.txt"):
        assert np.array_equal(read_transform(tmp_path / name), T)
    write_transform(tmp_path / "t.npy", T)
    write_transform(tmp_path / "t.txt", T)
    assert np.allclose(read_transform(tmp_path / "t.npy"), T)
    assert np.allclose(read_transform(tmp_path / "t.txt"), T)
    # A georeferenced result (a turn about a point 4e6 m out) reads back to the same bits: at 10
    # decimals its rotation had moved that point by 0.1 mm.
    S = rigid(np.eye(3), np.array([500_000.0, 4_000_000.0, 100.0]))
    geo = S @ rigid(euler_to_matrix([0.3, -0.2, 9.7]), np.array([1.5, -2.25, 0.1])) @ np.linalg.inv(S)
    write_transform(tmp_path / "geo.txt", geo)
    assert np.array_equal(np.loadtxt(tmp_path / "geo.txt"), geo)


def _rounded_georeferenced_truth(rng, folder, digits=6):
    """A truth of clouds 5e6 units from their frame's origin, written with `digits` decimals of
    its rotation (as published truths are) and its translation in full: ((4, 4) as written, the
    file, a point of the source)."""
    utm = np.array([500_000.0, 5_000_000.0, 300.0])
    S = np.eye(4)
    S[:3, 3] = utm
    T = S @ rigid(euler_to_matrix(rng.uniform(-40.0, 40.0, 3)), rng.uniform(-5.0, 5.0, 3)) @ np.linalg.inv(S)
    T[:3, :3] = np.round(T[:3, :3], digits)
    T[:3, 3] = utm - T[:3, :3] @ utm + rng.uniform(-5.0, 5.0, 3)  # the rounded rotation's own translation
    path = folder / "gt.txt"
    path.write_text("\n".join(" ".join(f"{v:.{digits if c < 3 and r < 3 else 10}f}" for c, v in enumerate(row)) for r, row in enumerate(T)) + "\n")
    return np.loadtxt(path), path, utm + rng.uniform(-20.0, 20.0, 3)


def test_a_rounded_rotation_made_exact_still_moves_the_clouds_where_the_file_does(tmp_path):
    rng = np.random.default_rng(4)
    for _ in range(5):
        written, path, centre = _rounded_georeferenced_truth(rng, tmp_path)
        exact = read_transform(path, about=centre)
        assert np.allclose(exact[:3, :3].T @ exact[:3, :3], np.eye(3), atol=1e-12)
        assert np.linalg.norm(apply_transform(exact, centre[None]) - apply_transform(written, centre[None])) < 1e-6
        # Made exact about the frame's origin, the same rotation moves the clouds by metres.
        assert np.linalg.norm(apply_transform(read_transform(path), centre[None]) - apply_transform(written, centre[None])) > 0.05
    # A poses file's (KITTI's 3x4 per line), each pose about its own scan.
    truths = [_rounded_georeferenced_truth(rng, tmp_path) for _ in range(2)]
    (tmp_path / "poses.txt").write_text("".join(" ".join(f"{v:.10f}" for v in written[:3].ravel()) + "\n" for written, _, _ in truths))
    for (written, _, centre), pose in zip(truths, read_poses(tmp_path / "poses.txt", ["a", "b"], [c for _, _, c in truths])):
        assert np.linalg.norm(apply_transform(pose, centre[None]) - apply_transform(written, centre[None])) < 1e-6


@pytest.mark.parametrize("ext", ["txt", "npy"])
def test_a_written_transform_reads_back_bit_for_bit(tmp_path, ext):
    from o3dsoft.transforms import nearest_rigid

    rng = np.random.default_rng(7)
    for k in range(20):  # rigid to float64 precision, as register's results are; some georeferenced
        T = nearest_rigid(rigid(euler_to_matrix(rng.uniform(-180.0, 180.0, 3)), rng.uniform(-5.0, 5.0, 3) + (k % 2) * np.array([5e5, 5e6, 300.0])))
        assert np.array_equal(read_transform(write_transform(tmp_path / f"T{k}.{ext}", T)), T)


@pytest.mark.parametrize(
    "text,match",
    [
        ("1 0 0 0\n0 1 x 0\n0 0 1 0\n0 0 0 1\n", r"line 2: 'x' is not a number"),
        ("1 0 0\n0 1 0\n0 0 1\n", r"line 1: 3 values; expected 4"),
        ("1 0 0 0\n0 1 0 0\n", r"shape \(2, 4\)"),
        ("2 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", "not orthonormal"),
        ("1 0 0 0\n0 1 0 0\n0 0 -1 0\n0 0 0 1\n", "reflection"),
        ("1 0 0 0\n0 1 0 0\n0 0 1 0\n1 0 0 1\n", "last row"),
        ("", "empty"),
    ],
)
def test_malformed_transforms(tmp_path, text, match):
    path = tmp_path / "T.txt"
    path.write_text(text)
    with pytest.raises(InputError, match=match) as err:
        read_transform(path)
    assert "T.txt" in str(err.value)


def test_unwritable_output_leaves_nothing(tmp_path, pts):
    with pytest.raises(InputError, match="does not exist"):
        write_points(tmp_path / "missing_dir" / "out.ply", pts)
    with pytest.raises(UsageError, match="unknown extension"):
        write_points(tmp_path / "out.off", pts)
    assert list(tmp_path.iterdir()) == []


def test_a_write_the_disk_cuts_short_leaves_nothing(tmp_path):
    """A file-size limit (RLIMIT_FSIZE) cuts every write short as a full disk does, in a child
    process so that pytest's own files are not limited."""
    import subprocess
    import sys

    script = f"""
import resource, signal, sys
import numpy as np
from o3dsoft.errors import InputError
from o3dsoft.io import write_points
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit then fails with EFBIG
resource.setrlimit(resource.RLIMIT_FSIZE, (20_000, 20_000))
points = np.random.default_rng(0).normal(size=(5000, 3))  # 120 kB as float64
failed = 0
for ext in (".ply", ".pcd", ".xyz", ".xyzn", ".pts", ".npy"):
    try:
        write_points({str(tmp_path)!r} + "/aligned" + ext, points)
    except InputError as e:
        failed += "cannot write" in str(e)
sys.exit(0 if failed == 6 else 1)
"""
    assert subprocess.run([sys.executable, "-c", script]).returncode == 0
    assert list(tmp_path.iterdir()) == []


def test_a_disk_that_cannot_hold_the_file_fails_before_the_rename(tmp_path, pts, monkeypatch):
    import errno
    import os

    def no_space(fd):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "fsync", no_space)
    for path in (tmp_path / "out.npy", tmp_path / "out.ply"):
        with pytest.raises(InputError, match="No space left"):
            write_points(path, pts)
    with pytest.raises(InputError, match="No space left"):
        write_transform(tmp_path / "T.txt", np.eye(4))
    assert list(tmp_path.iterdir()) == []


def test_a_full_tmpfs_leaves_nothing_under_the_final_name(tmp_path, pts):
    import subprocess

    mount = tmp_path / "full"
    mount.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=200k", "tmpfs", str(mount)], capture_output=True).returncode != 0:
        pytest.skip("cannot mount a tmpfs here (needs root)")
    try:
        (mount / "filler").write_bytes(b"\0" * 190_000)
        big = np.random.default_rng(0).normal(size=(2000, 3))  # 48 kB of float64 and more: does not fit
        for ext in (".ply", ".pcd", ".npy"):
            with pytest.raises(InputError):
                write_points(mount / f"aligned{ext}", big)
        assert [p.name for p in mount.iterdir()] == ["filler"]
    finally:
        subprocess.run(["umount", "--lazy", str(mount)], check=True)


def test_a_rounded_ground_truth_is_taken_as_the_nearest_rotation(tmp_path):
    rng = np.random.default_rng(0)
    from o3dsoft.transforms import euler_to_matrix

    R = euler_to_matrix(np.array([10.0, -35.0, 120.0]))
    rounded = np.round(R, 4)  # as published: about 1e-4 off orthonormal
    (tmp_path / "gt.txt").write_text("\n".join(" ".join(f"{v:.4f}" for v in row) for row in np.c_[rounded, rng.normal(size=3)]) + "\n0 0 0 1\n")
    T = read_transform(tmp_path / "gt.txt")
    assert np.abs(T[:3, :3].T @ T[:3, :3] - np.eye(3)).max() < 1e-12 and np.linalg.det(T[:3, :3]) > 0
    assert np.abs(T[:3, :3] - R).max() < 1e-4
    (tmp_path / "off.txt").write_text("1.01 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")  # 2e-2 off: a wrong file, not rounding
    with pytest.raises(InputError, match="off.txt: not a rigid transform"):
        read_transform(tmp_path / "off.txt")


def test_the_real_scans_ground_truths_read(tmp_path):
    from pathlib import Path

    folder = Path(__file__).resolve().parents[2] / "shared" / "data" / "real_scans" / "3dmatch_redkitchen"
    if not folder.is_dir():
        pytest.skip("no shared real scans here")
    for path in sorted(folder.glob("gt_*.txt")):
        T = read_transform(path)
        assert np.abs(T[:3, :3].T @ T[:3, :3] - np.eye(3)).max() < 1e-12


def test_las_keeps_large_coordinates_to_its_step(tmp_path, pts):
    # Survey coordinates (UTM, metres): the file stores integers from the cloud's corner.
    far = pts * 10 + np.array([512_345.0, 5_432_100.0, 230.0])
    back = read_points(write_points(tmp_path / "survey.las", far))
    assert np.abs(back - far).max() <= LAS_RESOLUTION / 2 + 1e-9


def test_las_keeps_a_cloud_in_large_units_to_a_millionth_of_its_size(tmp_path, pts):
    """A 2-unit cloud in units a thousand times larger (kilometres for metres) spans 0.002: at
    LAS_RESOLUTION it would keep a handful of distinct points, and written, read no more."""
    small = pts / 1000.0 + np.array([3.0, -7.0, 0.5])
    back = read_points(write_points(tmp_path / "small.las", small))
    extent = np.ptp(small, axis=0).max()
    assert len(np.unique(back, axis=0)) == len(np.unique(small, axis=0))
    assert np.abs(back - small).max() <= 1e-6 * extent


def test_laz_is_read(tmp_path, pts):
    import laspy

    las = laspy.read(write_points(tmp_path / "cloud.las", pts))
    las.write(tmp_path / "cloud.laz")  # compressed by the lazrs backend
    assert (tmp_path / "cloud.laz").stat().st_size > 0
    assert np.allclose(read_points(tmp_path / "cloud.laz"), pts, atol=LAS_RESOLUTION)


def test_las_without_points_is_refused(tmp_path):
    import laspy

    laspy.LasData(laspy.LasHeader(point_format=0, version="1.4")).write(tmp_path / "empty.las")
    with pytest.raises(InputError, match="empty.las: holds 0 points"):
        read_points(tmp_path / "empty.las")


def test_las_of_an_unknown_point_format_is_refused(tmp_path, pts):
    path = write_points(tmp_path / "odd.las", pts)
    data = bytearray(path.read_bytes())
    data[104] = 42  # the header's point data format ID (0-10 exist)
    path.write_bytes(bytes(data))
    with pytest.raises(InputError, match="odd.las: not a readable LAS/LAZ file"):
        read_points(path)


def _write_e57(path, clouds, translations, colours=None):
    """An E57 file of the (N, 3) `clouds`, each at its translation, with (N, 3) uint8 `colours`
    per cloud where given."""
    import pye57

    e57 = pye57.E57(str(path), mode="w")
    for k, (points, shift) in enumerate(zip(clouds, translations)):
        data = {"cartesianX": points[:, 0], "cartesianY": points[:, 1], "cartesianZ": points[:, 2]}
        if colours is not None:
            data.update(colorRed=colours[k][:, 0], colorGreen=colours[k][:, 1], colorBlue=colours[k][:, 2])
        e57.write_scan_raw(data, name=f"station {k}", rotation=np.array([1.0, 0.0, 0.0, 0.0]), translation=np.asarray(shift, dtype=float))
    e57.close()
    return path


def test_e57_gives_every_scan_in_the_files_frame(tmp_path, pts):
    path = _write_e57(tmp_path / "survey.e57", [pts, pts[:150]], [(0, 0, 0), (5, 0, 0)])
    scans = read_scans(path)
    assert [name for name, _ in scans] == [f"{path}#0", f"{path}#1"]
    assert np.allclose(scans[0][1], pts)
    assert np.allclose(scans[1][1], pts[:150] + [5, 0, 0])  # the scan's pose applied
    with pytest.raises(InputError, match="holds 2 scans.*multiway"):
        read_points(path)


def test_e57_of_one_scan_reads_as_a_cloud(tmp_path, pts):
    path = _write_e57(tmp_path / "one.e57", [pts], [(0, 0, 1)])
    assert np.allclose(read_points(path), pts + [0, 0, 1])
    assert [name for name, _ in read_scans(path)] == [str(path)]


def test_a_broken_e57_is_refused_in_one_line(tmp_path):
    path = tmp_path / "broken.e57"
    path.write_bytes(b"ASTM-E57" + bytes(200))
    with pytest.raises(InputError, match="broken.e57: not a readable E57 file") as info:
        read_scans(path)
    assert "\n" not in str(info.value)


def test_clouds_far_from_their_origin_keep_their_points_and_normals_in_pcd_and_xyzn(tmp_path, pts):
    far = pts + [500_000.0, 5_000_000.0, 300.0]  # georeferenced: float32 steps by 0.5 units there
    for name, cloud, size in (("near.pcd", pts, "SIZE 4 4 4"), ("far.pcd", far, "SIZE 8 8 8")):
        write_points(tmp_path / name, cloud, colors=np.full(cloud.shape, 0.5))
        assert size in (tmp_path / name).read_bytes()[:300].decode("ascii", errors="replace")
        assert np.allclose(read_points(tmp_path / name), cloud, rtol=0, atol=1e-6)
        assert np.allclose(read_attributes(tmp_path / name, len(cloud)).colors, 128 / 255)
    write_points(tmp_path / "near.xyzn", pts)
    write_points(tmp_path / "far.xyzn", far)
    near, moved = np.loadtxt(tmp_path / "near.xyzn")[:, 3:], np.loadtxt(tmp_path / "far.xyzn")[:, 3:]
    assert np.all(np.abs(np.sum(near * moved, axis=1)) > 0.999)  # the same surface, the same normals


def _pcd(path, fields, rows, data="binary"):
    """A PCD file of the numpy record `rows`, whose fields are (name, SIZE, TYPE) in `fields`."""
    header = (
        f"VERSION 0.7\nFIELDS {' '.join(f[0] for f in fields)}\nSIZE {' '.join(str(f[1]) for f in fields)}\nTYPE {' '.join(f[2] for f in fields)}\n"
        f"COUNT {' '.join('1' for _ in fields)}\nWIDTH {len(rows)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(rows)}\nDATA {data}\n"
    )
    path.write_bytes(header.encode("ascii") + rows.tobytes())
    return path


def test_an_organised_pcd_moved_keeps_its_rows_and_its_invalid_points(tmp_path):
    from o3dsoft.io import write_moved

    rng = np.random.default_rng(2)
    grid = rng.uniform(-1.0, 1.0, (8 * 25, 3))
    grid[rng.random(len(grid)) < 0.1] = np.nan  # no return: kept as NaN where the range image has the pixel
    source = write_points(tmp_path / "scan.pcd", grid, width=25)
    assert "WIDTH 25\nHEIGHT 8\n" in source.read_bytes()[:400].decode("ascii", "replace")
    read = read_points(source)
    assert read.shape == grid.shape and np.array_equal(np.isnan(read), np.isnan(grid))
    T = rigid(euler_to_matrix([10.0, 20.0, 30.0]), [1.0, 2.0, 3.0])
    moved = write_moved(tmp_path / "moved.pcd", source, read, T)
    assert "WIDTH 25\nHEIGHT 8\n" in moved.read_bytes()[:400].decode("ascii", "replace")
    again = read_points(moved)
    assert np.array_equal(np.isnan(again), np.isnan(grid)) and np.allclose(
        again[~np.isnan(grid).any(axis=1)], apply_transform(T, grid)[~np.isnan(grid).any(axis=1)], atol=1e-5
    )
    flat = write_moved(tmp_path / "moved.ply", source, read, T)  # other formats: the points in one list, as before
    assert read_points(flat).shape[0] <= len(grid)
    with pytest.raises(ValueError, match="width must divide the 200 points into rows, got 30"):
        write_points(tmp_path / "bad.pcd", grid, width=30)


def test_a_pcd_of_double_coordinates_is_read_as_written(tmp_path, pts):
    """PCL writes 8-byte x, y, z (georeferenced clouds); Open3D's binary reader gives other numbers."""
    rows = np.zeros(len(pts), dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("intensity", "<f4"), ("ring", "<u2")])
    far = pts + [500_000.0, 5_000_000.0, 300.0]
    rows["x"], rows["y"], rows["z"] = far.T
    fields = [("x", 8, "F"), ("y", 8, "F"), ("z", 8, "F"), ("intensity", 4, "F"), ("ring", 2, "U")]
    assert np.array_equal(read_points(_pcd(tmp_path / "wide.pcd", fields, rows)), far)
    with pytest.raises(InputError, match="compressed.pcd: x, y, z are 8-byte floats in binary_compressed data"):
        read_points(_pcd(tmp_path / "compressed.pcd", fields, rows, data="binary_compressed"))
    cut = _pcd(tmp_path / "cut.pcd", fields, rows)
    cut.write_bytes(cut.read_bytes()[: -50 * rows.itemsize])
    with pytest.raises(InputError, match="cut.pcd: the header declares 200 points, but the file ends after 150"):
        read_points(cut)
    flat = np.zeros(len(pts), dtype=[("x", "<f4"), ("y", "<f4")])  # a 2D scan's x and y alone
    flat["x"], flat["y"] = pts[:, 0], pts[:, 1]
    with pytest.raises(InputError, match="flat.pcd: its FIELDS are x y: no z; expected x, y and z"):
        read_points(_pcd(tmp_path / "flat.pcd", [("x", 4, "F"), ("y", 4, "F")], flat))


def test_a_las_of_a_cloud_spanning_more_than_its_integers_hold_at_the_finest_step_is_written_coarser(tmp_path, pts):
    wide = pts * 1e5  # about 5e5 units across: over 2^31 steps of 1e-4
    write_points(tmp_path / "wide.las", wide)
    step = (np.ptp(wide, axis=0) + 1.0) / (2**31 - 1)
    assert np.all(np.abs(read_points(tmp_path / "wide.las") - wide) <= step)
    write_points(tmp_path / "small.las", pts)
    assert np.all(np.abs(read_points(tmp_path / "small.las") - pts) <= LAS_RESOLUTION / 2 + 1e-12)


def test_colours_are_written_from_0_1_or_bytes_and_other_ranges_are_refused(tmp_path, pts):
    write_points(tmp_path / "bytes.ply", pts, colors=np.full(pts.shape, 200, dtype=np.uint8))  # as images store them
    assert np.allclose(read_attributes(tmp_path / "bytes.ply", len(pts)).colors, 200 / 255)
    rgb = np.random.default_rng(3).integers(0, 256, pts.shape).astype(np.uint8)
    write_points(tmp_path / "coloured.las", pts, colors=rgb)  # LAS holds colours too (16-bit)
    assert np.allclose(read_attributes(tmp_path / "coloured.las", len(pts)).colors, rgb / 255)
    assert np.allclose(read_points(tmp_path / "coloured.las"), pts, atol=1e-4)
    write_points(tmp_path / "coloured.pts", pts, colors=rgb)  # x y z r g b, as Open3D and CloudCompare read it
    assert np.allclose(read_attributes(tmp_path / "coloured.pts", len(pts)).colors, rgb / 255)
    assert np.allclose(read_points(tmp_path / "coloured.pts"), pts, atol=1e-9)
    write_points(tmp_path / "plain.pts", pts)
    assert read_attributes(tmp_path / "plain.pts", len(pts)).colors is None
    with pytest.raises(ValueError, match="colors must be in 0-1 \\(or uint8 in 0-255\\), got values up to 200"):
        write_points(tmp_path / "floats.ply", pts, colors=np.full(pts.shape, 200.0))
    with pytest.raises(ValueError, match="points must be \\(N, 3\\), got \\(200, 2\\)"):
        write_points(tmp_path / "flat.ply", pts[:, :2])
    assert not (tmp_path / "floats.ply").exists() and not (tmp_path / "flat.ply").exists()


def _cube_faces(points):
    """How many of the (N, 3) points lie on each of the six faces of the cube [-1, 1]^3."""
    return [int((np.abs(points[:, k] - side) < 1e-9).sum()) for k in range(3) for side in (-1.0, 1.0)]


def test_meshes_of_quads_open3d_reads_in_part_are_read_whole(tmp_path):
    corners = [(-1, -1, -1), (1, -1, -1), (1, 1, -1), (-1, 1, -1), (-1, -1, 1), (1, -1, 1), (1, 1, 1), (-1, 1, 1)]
    quads = [(0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (2, 3, 7, 6), (1, 2, 6, 5), (3, 0, 4, 7)]
    vertices = "".join(f"v {x} {y} {z}\n" for x, y, z in corners)
    a, b, c, d = (i + 1 for i in quads[0])
    # An OBJ of triangles and quads (as Blender exports): Open3D keeps the triangles only.
    (tmp_path / "mixed.obj").write_text(
        vertices + f"f {a} {b} {c}\nf {a} {c} {d}\n" + "".join("f " + " ".join(str(i + 1) for i in q) + "\n" for q in quads[1:])
    )
    # An OFF whose second face, a quad with a repeated corner, Open3D cannot split: it keeps the first.
    body = "".join(f"{x} {y} {z}\n" for x, y, z in corners)
    faces = ["4 " + " ".join(map(str, quads[0])), "4 1 2 2 6"] + ["4 " + " ".join(map(str, q)) for q in quads[1:]]
    (tmp_path / "stops.off").write_text(f"OFF\n8 {len(faces)} 0\n{body}" + "\n".join(faces) + "\n")
    for name in ("mixed.obj", "stops.off"):
        assert min(_cube_faces(read_points(tmp_path / name, mesh_points=3000))) > 300, name  # every face, about 500 points each


def test_the_colours_of_e57_scans_and_leica_pts_files_are_read(tmp_path, pts):
    rng = np.random.default_rng(5)
    colours = [rng.integers(0, 256, (len(pts), 3)).astype(np.uint8), rng.integers(0, 256, (150, 3)).astype(np.uint8)]
    one = _write_e57(tmp_path / "one.e57", [pts], [(0, 0, 0)], colours[:1])
    assert np.allclose(read_attributes(one, len(pts)).colors, colours[0] / 255)
    survey = _write_e57(tmp_path / "survey.e57", [pts, pts[:150]], [(0, 0, 0), (5, 0, 0)], colours)
    assert np.allclose(read_attributes(survey, 150, scan=1).colors, colours[1] / 255)
    assert read_attributes(survey, 150).colors is None  # which of its scans: not said
    rows = "".join(f"{x:.6f} {y:.6f} {z:.6f} -100 {r} {g} {b}\n" for (x, y, z), (r, g, b) in zip(pts, colours[0]))
    (tmp_path / "leica.pts").write_text(f"{len(pts)}\n{rows}")  # x y z intensity r g b
    assert np.allclose(read_points(tmp_path / "leica.pts"), pts, atol=1e-6)
    assert np.allclose(read_attributes(tmp_path / "leica.pts", len(pts)).colors, colours[0] / 255)
    (tmp_path / "nocount.pts").write_text(rows)
    with pytest.raises(InputError, match="nocount.pts: its first line .* is a point, not the point count a .pts file starts with"):
        read_points(tmp_path / "nocount.pts")


def test_quiet_c_output_blocks_that_overlap_across_threads_give_the_stream_back():
    """Two threads silence stdout (the file readers, KISS-Matcher) and leave in the order they
    came, not nested: the process's stdout must be its own again afterwards, not /dev/null."""
    out = python_output(
        """
import threading
from o3dsoft.io import quiet_c_output
entered, leave = threading.Event(), threading.Event()
def first():
    with quiet_c_output("stdout"):
        entered.set()
        leave.wait()
thread = threading.Thread(target=first)
thread.start()
entered.wait()
with quiet_c_output("stdout"):  # entered second, left first
    leave.set()
    thread.join()
print("stdout is back")
""",
        timeout=120,
    )
    assert out.strip() == "stdout is back", out


def _float32_ply(path, points):
    """A binary PLY of float32 x, y, z (as many scanners and tools write)."""
    rows = np.asarray(points, dtype="<f4")
    header = f"ply\nformat binary_little_endian 1.0\nelement vertex {len(rows)}\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    path.write_bytes(header.encode("ascii") + rows.tobytes())
    return path


def test_float32_files_far_from_their_origin_say_how_much_they_were_rounded(tmp_path, pts):
    from click.testing import CliRunner

    from o3dsoft.cli.main import main
    from o3dsoft.io import float32_rounding, stored_as_float32

    far = pts + [500_000.0, 4_000_000.0, 100.0]
    f32 = _float32_ply(tmp_path / "far32.ply", far)
    read = read_points(f32)
    assert stored_as_float32(f32) and float32_rounding(f32, read) == 0.125  # half of float32's step at 4e6
    near = _float32_ply(tmp_path / "near32.ply", pts)
    assert stored_as_float32(near) and float32_rounding(near, read_points(near)) is None  # rounds by 1e-7 of its size at most
    write_points(tmp_path / "far64.ply", far)
    assert not stored_as_float32(tmp_path / "far64.ply") and float32_rounding(tmp_path / "far64.ply", far) is None
    write_points(tmp_path / "near.pcd", pts)  # float32 PCD near the origin, float64 far from it
    write_points(tmp_path / "far.pcd", far)
    assert stored_as_float32(tmp_path / "near.pcd") and not stored_as_float32(tmp_path / "far.pcd")
    np.savetxt(tmp_path / "far.xyz", far)
    assert float32_rounding(tmp_path / "far.xyz", far) is None  # text keeps its digits
    r = CliRunner().invoke(main, ["register", str(f32), str(f32), "--no-refine", "--search", "off"])
    assert f"Warning: {f32} stores x, y, z as float32, which 4,000," in r.output and "rounds them by up to 0.125 units" in r.output
