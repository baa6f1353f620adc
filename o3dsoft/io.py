"""Reading and writing point clouds and transforms.

Point clouds are read through Open3D: PLY, PCD, XYZ, XYZN, XYZRGB, PTS as points, and meshes
(OFF, OBJ, STL, and PLY/GLB/GLTF with faces) sampled uniformly on their faces, as the paper did;
plus delimited text (``.csv``, ``.txt``: x, y, z columns), NumPy ``.npy`` arrays of shape (N, 3), LAS/LAZ through laspy (LAZ with its lazrs backend),
and E57 through pye57 (every scan of a file: :func:`read_scans`). Transforms are 4x4 text (whitespace or comma
separated) or ``.npy``. Files are written by o3dsoft itself (:func:`write_points`), to a temporary
file that is flushed to the disk and then renamed, so a failure (a full disk included) never
leaves a half-written output.
"""

from __future__ import annotations

import json
import os
import re
import sys
import tempfile
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Dict, Iterator, List, NamedTuple, Optional, Sequence, Tuple, Union

import numpy as np

from .errors import InputError, UsageError, first_line
from .transforms import apply_transform, nearest_rigid

PathLike = Union[str, Path]

POINT_EXTENSIONS = (".ply", ".pcd", ".xyz", ".xyzn", ".xyzrgb", ".pts")
MESH_ONLY_EXTENSIONS = (".off", ".obj", ".stl", ".glb", ".gltf", ".fbx")
SCANNER_EXTENSIONS = (".las", ".laz", ".e57")
TABLE_EXTENSIONS = (".csv", ".txt")  # delimited text: CloudCompare's and PDAL's exports
READ_EXTENSIONS = POINT_EXTENSIONS + MESH_ONLY_EXTENSIONS + SCANNER_EXTENSIONS + TABLE_EXTENSIONS + (".npy",)
WRITE_EXTENSIONS = (".ply", ".pcd", ".xyz", ".xyzn", ".pts", ".csv", ".npy", ".las")
LAS_RESOLUTION = 1e-4  # coordinate step of the LAS files written (file units: 0.1 mm for metres), or finer: _las_steps
DEFAULT_MESH_POINTS = 20_000
READ_TOLERANCE = 1e-3  # |R^T R - I| a transform file may have (rounded published ground truths)


def _o3d():
    from ._open3d import open3d

    return open3d


def check_extension(path: Path, allowed, what: str) -> str:
    """`path`'s extension, lower case; UsageError where it is not one of `allowed` for `what`, or
    `path` is a folder."""
    if path.is_dir():
        raise UsageError(f"{path}: is a folder, not a file")
    ext = path.suffix.lower()
    if ext not in allowed:
        raise UsageError(f"{path}: unknown extension {ext or '(none)'!r} for {what}; expected one of {', '.join(allowed)}")
    return ext


def check_readable(path: Path) -> None:
    """Raise UsageError where `path` does not exist or is a folder, InputError where it cannot be read."""
    if not path.exists():
        pattern = any(c in path.name for c in "*?[")  # a shell pattern that matched no file is passed on as written
        raise UsageError(f"{path}: no such file" + (" (a pattern that matched no file)" if pattern else ""))
    if path.is_dir():
        raise UsageError(f"{path}: is a folder, not a file")
    if not os.access(path, os.R_OK):
        raise InputError(f"{path}: permission denied")


_PLY_NUMPY = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2"}
_PLY_NUMPY.update({"int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"})
_PLY_SIZES = {kind: int(code[1]) for kind, code in _PLY_NUMPY.items()}
# Open3D's PLY reader moves on to the next point at the last property of each of these as it
# names them (z, nz, blue): a file that stores that one before the others has its points mixed.
_OPEN3D_TRIPLES = (("x", "y", "z"), ("nx", "ny", "nz"), ("red", "green", "blue"))

PlyElement = Tuple[str, int, List[Tuple[str, str, List[str]]]]  # name, count, [(type, name, a list's types), ...]
PlyHeader = Tuple[str, List[PlyElement], int]  # format, elements, byte offset of the data


def _ply_header(path: Path) -> Optional[PlyHeader]:
    """A PLY's format ("ascii", "binary_little_endian", ...), its elements and the byte offset
    of its data; None where the header cannot be read (Open3D's reader reports it)."""
    with open(path, "rb") as f:
        head = f.read(65536)
    end = head.find(b"end_header")
    data_start = head.find(b"\n", end) + 1
    if not head.startswith(b"ply") or end < 0 or data_start == 0:
        return None
    form = ""
    elements: List[PlyElement] = []
    for line in head[:end].decode("ascii", errors="replace").splitlines():
        words = line.split()
        if words[:1] == ["format"] and len(words) >= 2:
            form = words[1]
        elif words[:1] == ["element"] and len(words) >= 3 and words[2].isdigit():
            elements.append((words[1], int(words[2]), []))
        elif words[:1] == ["property"] and len(words) >= 3 and elements:
            elements[-1][2].append((words[1], words[-1], words[2:-1]))
    return form, elements, data_start


def _open3d_misreads_ply(elements: List[PlyElement]) -> bool:
    """Whether the vertices store z before x or y (nz, blue likewise), which Open3D mixes up."""
    vertex = next((properties for name, _, properties in elements if name == "vertex"), [])
    order = [name for _, name, _ in vertex]
    for triple in _OPEN3D_TRIPLES:
        if all(name in order for name in triple) and order.index(triple[2]) < max(order.index(triple[0]), order.index(triple[1])):
            return True
    return False


def _ply_vertex_columns(path: Path, header: PlyHeader) -> Optional[Dict[str, np.ndarray]]:
    """Every scalar property of the vertices of the PLY `path` (its :func:`_ply_header`), by name,
    (N,) each as stored; None where the vertices are not the file's first element or hold a list
    (not read here)."""
    form, elements, data_start = header
    if not elements or elements[0][0] != "vertex" or any(kind not in _PLY_NUMPY for kind, _, _ in elements[0][2]):
        return None
    _, count, properties = elements[0]
    if form == "ascii":
        with open(path, "rb") as f:
            header_lines = f.read(data_start).count(b"\n")
        table = np.loadtxt(path, dtype=np.float64, skiprows=header_lines, max_rows=count, ndmin=2)
        return {name: table[:, i] for i, (_, name, _) in enumerate(properties)}
    order = {"binary_little_endian": "<", "binary_big_endian": ">"}.get(form)
    if order is None:
        return None
    record = np.dtype([(name, order + _PLY_NUMPY[kind]) for kind, name, _ in properties])
    table = np.fromfile(path, dtype=record, count=count, offset=data_start)
    return {name: table[name] for name in record.names}


def _ply_vertex_types(elements: List[PlyElement]) -> Dict[str, np.dtype]:
    """The numpy type of each scalar property of a PLY's vertices, by name."""
    vertex = next((properties for name, _, properties in elements if name == "vertex"), [])
    return {name: np.dtype(_PLY_NUMPY[kind]) for kind, name, _ in vertex if kind in _PLY_NUMPY}


def _check_ply(path: Path) -> None:
    """Raise InputError where a PLY's vertices lack an x, y or z property, or where the file ends
    before its last vertex (Open3D reads the missing values as whatever memory held, or zeros) or
    face (Open3D samples the faces it read: a part of the surface). A file whose header cannot be
    read is left to Open3D's reader (which reports it)."""
    header = _ply_header(path)
    if header is None:
        return
    form, elements, data_start = header
    names = [i for i, element in enumerate(elements) if element[0] == "vertex"]
    if not names:
        return
    vertex = names[0]
    properties = {name for kind, name, _ in elements[vertex][2] if kind != "list"}
    missing = [axis for axis in "xyz" if axis not in properties]
    if missing:
        raise InputError(
            f"{path}: its vertices have no {', '.join(missing)} property (the header names {', '.join(sorted(properties)) or 'none'}); expected x, y and z"
        )
    if form == "ascii":  # one line per element, so faces too are counted
        start, rest = data_start, elements
        first = elements[0]
        if first[0] == "vertex" and all(kind != "list" for kind, _, _ in first[2]):  # each vertex line: exactly its properties
            start, rest = _check_rows(path, data_start, first[1], len(first[2]), "vertices", exact=True), elements[1:]
        lines = _lines_from(path, start)
        for name, declared, _ in rest:
            _check_whole(path, declared, lines, {"vertex": "vertices", "face": "faces"}.get(name, f"'{name}' elements"))
            lines -= declared
        return
    before = elements[: vertex + 1]  # the elements the vertices' end depends on
    count = elements[vertex][1]
    if not form.startswith("binary") or not all(kind in _PLY_SIZES for element in before for kind, _, _ in element[2]):
        return  # list properties before the vertices: their size is not known without reading them
    rows = [sum(_PLY_SIZES[kind] for kind, _, _ in element[2]) for element in before]
    size = path.stat().st_size - data_start - sum(n * row for (_, n, _), row in zip(before[:-1], rows[:-1]))
    _check_whole(path, count, size // rows[-1] if rows[-1] else count, "vertices")
    if len(elements) > vertex + 1 and elements[vertex + 1][0] == "face":
        _, faces, properties = elements[vertex + 1]
        least = _least_face_bytes(properties)  # a face holds at least 3 vertex indices
        if least:
            _check_whole(path, faces, (size - count * rows[-1]) // least, "faces")


def _least_face_bytes(properties) -> int:
    """The fewest bytes a binary PLY face with these properties takes (a polygon has at least 3
    vertex indices; any other list may be empty); 0 where a type is unknown."""
    least = 0
    for kind, name, types in properties:
        if kind == "list":
            sizes = [_PLY_SIZES.get(t, 0) for t in types] if len(types) == 2 else [0]
            here = sizes[0] + (3 * sizes[-1] if name in ("vertex_indices", "vertex_index") else 0)
        else:
            sizes = [_PLY_SIZES.get(kind, 0)]
            here = sizes[0]
        if not all(sizes):
            return 0
        least += here
    return least


def _pcd_header(path: Path) -> Optional[Tuple[Dict[str, List[str]], int]]:
    """A PCD file's header lines by keyword (FIELDS, SIZE, TYPE, COUNT, POINTS, DATA, ...) and
    the offset of the first byte after it; None where no DATA line ends it."""
    with open(path, "rb") as f:
        head = f.read(65536)
    fields, data_start = {}, -1
    for line in head.split(b"\n"):
        words = line.decode("ascii", errors="replace").split()
        data_start += len(line) + 1
        if words and not words[0].startswith("#"):
            fields[words[0].upper()] = words[1:]
        if words[:1] == ["DATA"]:
            return fields, data_start + 1
    return None


def _pcd_record(fields: Dict[str, List[str]]) -> Optional[np.dtype]:
    """The numpy record of one point of a binary PCD of these header `fields`; None where the
    header does not describe one (Open3D then says what is wrong)."""
    names, sizes, types = fields.get("FIELDS", []), fields.get("SIZE", []), fields.get("TYPE", [])
    counts = fields.get("COUNT", ["1"] * len(names))
    kinds = {("F", "4"): "<f4", ("F", "8"): "<f8", ("I", "1"): "i1", ("I", "2"): "<i2", ("I", "4"): "<i4", ("I", "8"): "<i8"}
    kinds.update({("U", "1"): "u1", ("U", "2"): "<u2", ("U", "4"): "<u4", ("U", "8"): "<u8"})
    if not names or not len(names) == len(sizes) == len(types) == len(counts) or not all(c.isdigit() and int(c) > 0 for c in counts):
        return None
    if any((t.upper(), z) not in kinds for t, z in zip(types, sizes)):
        return None
    return np.dtype([(f"{k}_{name}", kinds[t.upper(), z], (int(c),)) for k, (name, z, t, c) in enumerate(zip(names, sizes, types, counts))])


def _check_pcd(path: Path) -> None:
    """Raise InputError where a PCD file of ascii or binary data ends before its last point:
    Open3D reads the missing points of an ascii file as zeros."""
    found = _pcd_header(path)
    if found is None:
        return
    fields, data_start = found
    names = [name.lower() for name in fields.get("FIELDS", ["x", "y", "z"])]
    missing = [axis for axis in "xyz" if axis not in names]
    if missing:
        raise InputError(f"{path}: its FIELDS are {' '.join(fields.get('FIELDS', []))}: no {', '.join(missing)}; expected x, y and z")
    form, count = fields["DATA"][:1], fields.get("POINTS", [""])[0]
    if not count.isdigit():
        return
    count = int(count)
    if form == ["ascii"]:
        counts = fields.get("COUNT", ["1"] * len(names))
        if all(c.isdigit() for c in counts):  # each point line: at least its fields' values (and every one there)
            _check_rows(path, data_start, count, sum(map(int, counts)), "points")
            return
        have = _lines_from(path, data_start)
    elif form == ["binary"]:
        try:
            row = sum(int(size) * int(n) for size, n in zip(fields["SIZE"], fields.get("COUNT", ["1"] * len(fields["SIZE"]))))
        except (KeyError, ValueError):
            return
        have = (path.stat().st_size - data_start) // row if row > 0 else count
    else:  # compressed: Open3D's reader refuses a cut one
        return
    _check_whole(path, count, have, "points")


def _read_wide_pcd(path: Path) -> Optional[np.ndarray]:
    """(N, 3) float64 x, y, z of a PCD file whose coordinates are 8-byte floats, which Open3D's
    binary reader returns as other numbers (PCL writes them for georeferenced clouds); None for
    other PCD files (Open3D reads them).

    Raises:
        InputError: such coordinates in compressed data (not read here).
    """
    found = _pcd_header(path)
    if found is None:
        return None
    fields, data_start = found
    wide = {name for name, size, kind in zip(fields.get("FIELDS", []), fields.get("SIZE", []), fields.get("TYPE", [])) if (size, kind.upper()) == ("8", "F")}
    if not wide & {"x", "y", "z"} or fields["DATA"][:1] == ["ascii"]:
        return None
    if fields["DATA"][:1] != ["binary"]:
        raise InputError(
            f"{path}: x, y, z are 8-byte floats in {' '.join(fields['DATA'])} data, which o3dsoft does not read; save it with DATA binary or ascii"
        )
    record = _pcd_record(fields)
    if record is None or not {"x", "y", "z"} <= set(fields["FIELDS"]):
        raise InputError(f"{path}: PCD header does not describe x, y, z fields (FIELDS, SIZE, TYPE, COUNT)")
    count = int(fields.get("POINTS", ["0"])[0]) if fields.get("POINTS", ["0"])[0].isdigit() else 0
    rows = np.fromfile(path, dtype=record, count=count, offset=data_start)
    column = {name: record.names[k] for k, name in enumerate(fields["FIELDS"])}
    return np.column_stack([rows[column[c]][:, 0] for c in "xyz"]).astype(np.float64)


def _text_words(path: Path) -> List[List[str]]:
    """The words of a text mesh file's lines that hold any ('#' starts a comment)."""
    lines = [line.split("#", 1)[0].split() for line in path.read_bytes().decode("ascii", errors="replace").splitlines()]
    return [words for words in lines if words]


def _off_counts(lines: List[List[str]]) -> Optional[Tuple[int, int, int]]:
    """(vertices, faces, index of the first vertex line) a text OFF mesh's header declares, from
    its :func:`_text_words`; None for a binary OFF or a header not understood."""
    keyword = re.fullmatch(r"([A-Z4]*OFF)(\d*)", lines[0][0]) if lines else None
    if keyword is None or "BINARY" in lines[0]:
        return None
    inline = ([keyword.group(2)] if keyword.group(2) else []) + lines[0][1:]  # ModelNet40's "OFF490 518 0" too
    counts = inline or (lines[1] if len(lines) > 1 else [])  # the counts: on the keyword's line or the next
    if len(counts) < 2 or not (counts[0].isdigit() and counts[1].isdigit()):
        return None
    return int(counts[0]), int(counts[1]), 1 if inline else 2


def _check_off(path: Path) -> None:
    """Raise InputError where a text OFF mesh ends before the vertices and faces its counts line
    declares: Open3D samples the faces it read, a part of the surface."""
    lines = _text_words(path)
    declared = _off_counts(lines)
    if declared is None:
        return
    vertices, faces, first = declared
    body = len(lines) - first
    _check_whole(path, vertices, body, "vertices")
    _check_whole(path, faces, body - vertices, "faces")


def _declared_triangles(path: Path, ext: str) -> Optional[int]:
    """How many triangles the faces of a text OBJ or OFF mesh make (a face of n corners: n - 2);
    None for other files, binary ones and headers not understood."""
    if ext not in (".obj", ".off"):
        return None
    lines = _text_words(path)
    if ext == ".obj":
        return sum(len(words) - 3 for words in lines if words[0] == "f" and len(words) >= 4)
    declared = _off_counts(lines)
    if declared is None:
        return None
    vertices, faces, first = declared
    return sum(int(words[0]) - 2 for words in lines[first + vertices : first + vertices + faces] if words[0].isdigit() and int(words[0]) >= 3)


def _check_stl(path: Path) -> None:
    """Raise InputError where a binary STL ends before the triangles its header counts, or an
    ascii STL before its closing 'endsolid' line."""
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(84)
    declared = int(np.frombuffer(head[80:84], dtype="<u4")[0]) if len(head) == 84 else -1
    if declared >= 0 and 84 + 50 * declared == size:  # a whole binary STL (its 80-byte header may begin with "solid" too)
        return
    if head.lstrip().lower().startswith(b"solid") and b"\0" not in head:  # ascii: no count, but a closing line after the last facet
        with open(path, "rb") as f:
            f.seek(max(0, size - 4096))
            tail = f.read().lower()
        if tail.rfind(b"endsolid") <= tail.rfind(b"endfacet"):
            raise InputError(f"{path}: an ascii STL that ends before its closing 'endsolid' line; is it complete (a copy or a download cut short)?")
        return
    if declared >= 0:
        _check_whole(path, declared, (size - 84) // 50, "triangles")


# OBJ records with fewer fields than a mesh is read from: a vertex (v, vn) of under 3 numbers, a
# face of under 3 vertices, a texture coordinate of none.
_SHORT_OBJ_RECORD = re.compile(rb"^[ \t]*(?:(?:v|vn|f)(?:[ \t]+[^ \t\r\n]+){0,2}|vt)[ \t]*\r?$", re.MULTILINE)


def _check_obj(path: Path) -> None:
    """Raise InputError at the first OBJ record with fewer fields than its keyword needs: a file
    cut short in its last line, or a malformed line (OBJ declares no counts, and its readers skip
    such a line, so that the vertices after it shift and the faces join the wrong ones)."""
    text = path.read_bytes()
    short = _SHORT_OBJ_RECORD.search(text)
    if short is None:
        return
    line = text.count(b"\n", 0, short.start()) + 1
    record = short.group().split()
    keyword, found, fields = record[0].decode(), len(record) - 1, {b"vt": 1}.get(record[0], 3)
    if short.end() == len(text.rstrip(b"\r\n \t")) and not text.endswith((b"\n", b"\r")):  # the last line, unended
        raise InputError(
            f"{path}: line {line}: the file ends in the middle of a '{keyword}' record ({found} of its {fields} fields); "
            "is it complete (a copy or a download cut short)?"
        )
    raise InputError(f"{path}: line {line}: a '{keyword}' record with {found} field(s), expected at least {fields}; is the file damaged?")


# A .pts file's first line: the point count, as Open3D reads it (leading spaces, a "+", digits).
_PTS_COUNT = re.compile(rb"\s*\+?(\d+)")


def _check_pts(path: Path) -> None:
    """Raise InputError where a .pts file starts with a point instead of its count, or where one
    of the `count` lines after the count, which Open3D reads as points, is missing, blank or holds
    fewer than 3 numbers: Open3D takes such a point from whatever its memory held. Read line by
    line (such files run to gigabytes)."""
    with open(path, "rb") as f:
        first = f.readline()
        count = _PTS_COUNT.match(first)
        if count is None:
            return  # Open3D reads no point; the caller names the count line
        if _xyz_line(first):
            raise InputError(
                f"{path}: its first line {_shown(first)!r} is a point, not the point count a .pts file starts with; add the count, or save the file as .xyz"
            )
        declared = int(count.group(1))
        for n in range(declared):
            line = f.readline()
            if not line:
                _check_whole(path, declared, n, "points")
            if not _xyz_line(line):
                if not line.endswith(b"\n") and not f.read(1):
                    raise InputError(f"{path}: line {n + 2}: the file ends in the middle of a point; is it complete (a copy or a download cut short)?")
                raise InputError(f"{path}: line {n + 2}: {_shown(line)!r}; expected x y z (line 1 counts {declared} points, one a line)")


def _shown(line: bytes) -> str:
    """A line of a file as an error message quotes it: stripped, at most 60 characters."""
    return line.strip()[:60].decode("utf-8", errors="replace")


def _xyz_line(line: bytes) -> bool:
    """The line starts with at least 3 numbers."""
    fields = line.split()
    if len(fields) < 3:
        return False
    try:
        for v in fields[:3]:
            float(v)
    except ValueError:
        return False
    return True


def _check_rows(path: Path, start: int, count: int, values: int, noun: str, exact: bool = False) -> int:
    """Raise InputError where the text from byte `start` on holds fewer than `count` non-blank
    lines (one element each), or where one of them holds fewer than `values` values (another
    number where `exact`): Open3D fills such an element from whatever its memory held (a PCD
    point) or reads the values after it shifted (a PLY vertex). Read line by line; returns the
    offset of the byte after the last of those lines."""
    with open(path, "rb") as f:
        number = f.read(start).count(b"\n")  # the header's lines
        seen = 0
        while seen < count:
            line = f.readline()
            number += 1
            if not line:
                _check_whole(path, count, seen, noun)
            fields = line.split()
            if not fields:
                continue
            if len(fields) < values or (exact and len(fields) != values):
                if not line.endswith(b"\n") and not f.read(1):  # the last line, cut
                    _check_whole(path, count, seen, noun)
                raise InputError(f"{path}: line {number}: {_shown(line)!r} holds {len(fields)} values; the header's {noun} hold {values} each")
            seen += 1
        return f.tell()


def _lines_from(path: Path, start: int) -> int:
    """How many non-blank lines the file holds from byte `start` on (a text body: one element a line)."""
    return sum(1 for line in path.read_bytes()[start:].splitlines() if line.strip())


def _check_whole(path: Path, declared: int, have: int, noun: str) -> None:
    if have < declared:
        raise InputError(
            f"{path}: the header declares {declared} {noun}, but the file ends after {max(have, 0)}; is it complete (a copy or a download cut short)?"
        )


# What each format's header declares, checked against what the file holds before Open3D reads it.
_WHOLE_CHECKS = {".ply": _check_ply, ".pcd": _check_pcd, ".off": _check_off, ".stl": _check_stl, ".obj": _check_obj, ".pts": _check_pts}


def sample_mesh(vertices: np.ndarray, faces: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """n points uniformly distributed over the area of a triangle mesh (deterministic for a seed).

    Args:
        vertices: (V, 3); faces: (F, 3) vertex indices.
    Returns:
        (n, 3) float64 points.
    """
    import trimesh

    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
    points, _ = trimesh.sample.sample_surface(mesh, n, seed=seed)
    return np.asarray(points, dtype=np.float64)


def read_points(path: PathLike, mesh_points: int = DEFAULT_MESH_POINTS, seed: int = 0) -> np.ndarray:
    """Read a point cloud, or sample a mesh, as an (N, 3) float64 array.

    A PLY with faces is read as a mesh and sampled; without faces, as points. Non-finite rows are
    kept (the pipeline's clean stage drops and counts them).

    Args:
        path: the file.
        mesh_points: how many points to sample on a mesh's faces.
        seed: seed of the mesh sampling.
    Raises:
        UsageError: missing file or unknown extension.
        InputError: unreadable content, no points, or a mesh format with no faces.
    """
    path = Path(path)
    ext = check_extension(path, READ_EXTENSIONS, "a point cloud")
    check_readable(path)
    if ext == ".npy":
        return _read_npy_points(path)
    if ext in TABLE_EXTENSIONS:
        return _read_table(path)
    if ext in (".las", ".laz"):
        return _read_las(path)
    if ext == ".e57":
        scans = read_scans(path)
        if len(scans) > 1:
            raise InputError(f"{path}: holds {len(scans)} scans; register takes one cloud per file (o3dsoft multiway reads every scan of an E57)")
        return scans[0][1]
    o3d = _o3d()
    if ext in _WHOLE_CHECKS:
        _WHOLE_CHECKS[ext](path)
    wide = _read_wide_pcd(path) if ext == ".pcd" else None
    if wide is not None:
        if len(wide) == 0:
            raise InputError(f"{path}: parsed to 0 points; is it a valid PCD point cloud?")
        return wide
    if ext == ".ply":
        header = _ply_header(path)
        if header is not None and _open3d_misreads_ply(header[1]):
            return _read_ply_in_any_order(path, header, mesh_points, seed)
    if ext in MESH_ONLY_EXTENSIONS or ext == ".ply":
        with _open3d_quietly():
            mesh = o3d.io.read_triangle_mesh(str(path))
        vertices = np.asarray(mesh.vertices)
        faces = np.asarray(mesh.triangles)
        declared = _declared_triangles(path, ext)
        if 0 < len(faces) < (declared or 0):  # Open3D skips an OBJ's quads beside triangles, and an OFF's faces from one it cannot split
            vertices, faces = _trimesh_mesh(path)
            if len(faces) < declared:
                raise InputError(f"{path}: its faces make {declared} triangles, but only {len(faces)} could be read; save it with triangles only")
        if len(faces) > 0:
            return _sampled(path, vertices, faces, mesh_points, seed)
        if ext in MESH_ONLY_EXTENSIONS:
            vertices, faces = _trimesh_mesh(path)  # what Open3D refuses: no faces, or ModelNet40's "OFF490 518 0" header
            if len(faces) > 0:
                return _sampled(path, vertices, faces, mesh_points, seed)
            if len(vertices) == 0:
                raise InputError(f"{path}: could not read any vertex or face; is it a valid {ext[1:].upper()} file?")
            raise InputError(f"{path}: mesh has {len(vertices)} vertices but no faces; points are sampled on faces, so a mesh needs at least one")
    with _open3d_quietly():
        cloud = o3d.io.read_point_cloud(str(path), format="auto")
    points = np.asarray(cloud.points, dtype=np.float64)
    if len(points) == 0:
        first = " (its first line must be the point count)" if ext == ".pts" else ""
        raise InputError(f"{path}: parsed to 0 points; is it a valid {ext[1:].upper()} point cloud{first}?{_bad_text_line(path, ext, 0)}")
    bad = _bad_text_line(path, ext, len(points))
    if bad:  # a line Open3D skipped: the cloud would be read in part
        raise InputError(f"{path}: {len(points)} points read, but not every line.{bad}")
    return points


def _read_ply_in_any_order(path: Path, header: PlyHeader, mesh_points: int, seed: int) -> np.ndarray:
    """A PLY (its :func:`_ply_header`) whose vertices store z before x or y: its faces sampled
    where it has some (read by trimesh), else its vertices read here."""
    if any(name == "face" and count > 0 for name, count, _ in header[1]):
        return _sampled(path, *_trimesh_mesh(path), mesh_points, seed)
    columns = _ply_vertex_columns(path, header)
    if columns is None:
        raise InputError(f"{path}: its vertices store z before x or y, and come after another element or hold a list; save x, y, z first, in that order")
    return np.stack([columns[axis] for axis in "xyz"], axis=1).astype(np.float64)


def _sampled(path: Path, vertices: np.ndarray, faces: np.ndarray, n: int, seed: int) -> np.ndarray:
    """:func:`sample_mesh` of a mesh read from `path`, whose faces must name its vertices; the
    faces with a vertex whose coordinates are not finite are left out (one such vertex would make
    the total area, and so every sampled point, NaN)."""
    if len(vertices) == 0:
        raise InputError(f"{path}: mesh has faces but no vertices")
    outside = faces[(faces < 0) | (faces >= len(vertices))]
    if len(outside):
        raise InputError(
            f"{path}: a face refers to vertex {outside[0] + 1} (counting from 1), but {len(vertices)} vertices were read; is a vertex line malformed or missing?"
        )
    finite = np.isfinite(vertices).all(axis=1)
    if not finite.all():
        faces = faces[finite[faces].all(axis=1)]
        if len(faces) == 0:
            raise InputError(f"{path}: every face has a vertex with a non-finite coordinate (vertex {np.flatnonzero(~finite)[0] + 1}, counting from 1)")
    return sample_mesh(vertices, faces, n, seed)


TEXT_EXTENSIONS = (".xyz", ".xyzn", ".xyzrgb", ".pts")
# The fewest numbers a line of each text format holds (Open3D's readers read no more).
_TEXT_COLUMNS = {".xyz": 3, ".xyzn": 6, ".xyzrgb": 6, ".pts": 3}


def _bad_text_line(path: Path, ext: str, parsed: int) -> str:
    """For a text format whose lines Open3D did not all read (it skips those it cannot parse):
    where the first such line is, as " Line N: '...'; expected ..."; "" where every line after a
    header (the lines before the first of numbers; for .pts, also the point count) became a point,
    and for other formats."""
    if ext not in TEXT_EXTENSIONS:
        return ""
    data = path.read_bytes()
    columns = _TEXT_COLUMNS[ext]

    def numbers(line: str) -> bool:  # as Open3D reads them: a quoted number is no number
        fields = line.split()
        return len(fields) >= columns and all(_is_float(v) for v in fields)

    header = not numbers(data.split(b"\n", 1)[0].decode("utf-8", errors="replace"))
    if data.count(b"\n") + (not data.endswith(b"\n")) <= parsed + header:  # every line a point, or the header
        return ""
    lines = [(n, line.strip()) for n, line in enumerate(data.decode("utf-8", errors="replace").splitlines(), start=1) if line.strip()]
    first = next((i for i, (_, line) in enumerate(lines) if numbers(line)), 0)
    body = lines[first:]  # after a header (and .pts's count), where there are points at all
    if len(body) <= parsed:
        return ""
    for number, line in body:
        if not numbers(line):
            return f" Line {number}: {line[:60]!r}; expected {columns} numbers separated by spaces ({len(body) - parsed} {'line' if len(body) - parsed == 1 else 'lines'} not read)"
    return ""


_DELIMITERS = (",", ";", "\t", None)  # None: runs of spaces


def _read_table(path: Path) -> np.ndarray:
    """x, y, z of a delimited text file: numbers separated by commas, semicolons, tabs or spaces
    (the first line of numbers decides which; decimal commas where no line reads otherwise), after
    any header lines. Where the last header line names columns x, y and z (any case, quoted or
    not, CloudCompare's "//X"), those are read; otherwise the first three. Every later non-blank
    line must hold them."""
    lines = path.read_text(encoding="utf-8-sig", errors="replace").splitlines()
    found = _first_numbers(lines, _DELIMITERS)
    if found is None:  # decimal commas (a spreadsheet's export in many locales: "1,5;2,5;3,5"): read as points
        lines = [line.replace(",", ".") for line in lines]
        found = _first_numbers(lines, _DELIMITERS[1:])
    if found is None:
        raise InputError(f"{path}: no line of at least 3 numbers separated by commas, semicolons, tabs or spaces")
    first, delimiter = found
    header = [line for line in lines[:first] if line.strip()]
    names = [name.strip().strip("\"'").lstrip("/").strip().lower() for name in header[-1].split(delimiter)] if header else []
    named = all(axis in names for axis in "xyz")
    columns = [names.index(axis) for axis in "xyz"] if named else [0, 1, 2]
    try:  # NumPy's parser first (2.5 times as fast); the loop below names the line it refuses
        return np.loadtxt(lines[first:], delimiter=delimiter, usecols=columns, quotechar='"', ndmin=2, dtype=np.float64)
    except ValueError:
        pass
    points = []
    for number, line in enumerate(lines[first:], start=first + 1):
        if not line.strip():
            continue
        fields = line.split(delimiter)
        point = _numbers([fields[c] for c in columns if c < len(fields)], 3)
        if point is None:
            where = "its columns x, y, z" if named else "3 numbers"
            sep = {",": "commas", ";": "semicolons", "\t": "tabs", None: "spaces"}[delimiter]
            raise InputError(f"{path}: line {number}: {line.strip()[:60]!r}; expected {where} separated by {sep}, as on line {first + 1}")
        points.append(point)
    return np.array(points, dtype=np.float64)


def _first_numbers(lines: List[str], delimiters) -> Optional[Tuple[int, Optional[str]]]:
    """(index, delimiter) of the first line that splits into at least 3 numbers by one of
    `delimiters` (tried in order); None where no line does."""
    return next(((i, d) for i, line in enumerate(lines) for d in delimiters if _numbers(line.split(d), 3)), None)


def _numbers(fields: List[str], count: int) -> Optional[List[float]]:
    """The fields as numbers (quotes and spaces around them ignored) where there are at least
    `count` and all are numbers; else None."""
    if len(fields) < count:
        return None
    try:
        return [float(field.strip().strip("\"'")) for field in fields]
    except ValueError:
        return None


_C_OUTPUT_LOCK = threading.Lock()
_C_OUTPUT: Dict[int, List[int]] = {}  # file descriptor -> [blocks open across threads, the stream's own descriptor]


@contextmanager
def quiet_c_output(name: str = "stderr") -> Iterator[None]:
    """Silence what C code writes to the process's stderr or stdout (`name`) within the block:
    Open3D's PLY reader prints "RPly: ..." lines for a bad file; o3dsoft
    reports problems itself, in one line. The descriptor is the process's: while a block
    of any thread is open, everything written to it is lost, and it comes back once the last
    block ends."""
    stream = getattr(sys, name)
    try:
        fd = stream.fileno()
    except (AttributeError, OSError, ValueError):  # no real stream (e.g. captured by a test runner)
        yield
        return
    stream.flush()
    with _C_OUTPUT_LOCK:
        held = _C_OUTPUT.get(fd)
        if held is None:
            held = _C_OUTPUT[fd] = [0, os.dup(fd)]
            with open(os.devnull, "w") as devnull:
                os.dup2(devnull.fileno(), fd)
        held[0] += 1
    try:
        yield
    finally:
        with _C_OUTPUT_LOCK:
            held[0] -= 1
            if held[0] == 0:
                os.dup2(held[1], fd)
                os.close(held[1])
                del _C_OUTPUT[fd]


@contextmanager
def _open3d_quietly() -> Iterator[None]:
    """What Open3D prints while it reads a file, off: its C code's stderr (RPly's lines) and its
    warnings, for this block only."""
    from ._open3d import quiet

    with quiet_c_output(), quiet():
        yield


def _trimesh_mesh(path: Path) -> Tuple[np.ndarray, np.ndarray]:
    """(V, 3) vertices and (F, 3) faces of a mesh file that Open3D refused (it rejects meshes with no
    faces, and OFF headers with the counts on the keyword's line), via trimesh; empty where it
    cannot read them either."""
    import trimesh

    nothing = (np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64))
    try:
        loaded = trimesh.load(str(path), process=False)  # vertices without faces load as a PointCloud
        if isinstance(loaded, trimesh.Scene):
            loaded = loaded.dump(concatenate=True) if loaded.geometry else None
        vertices = getattr(loaded, "vertices", None)
        if vertices is None:
            return nothing
        faces = getattr(loaded, "faces", None)
        faces = np.zeros((0, 3), dtype=np.int64) if faces is None else np.asarray(faces, dtype=np.int64).reshape(-1, 3)
        return np.asarray(vertices, dtype=np.float64).reshape(-1, 3), faces
    except Exception:  # any parse failure (a vertex line of two numbers reshapes to no (V, 3)) means: no usable mesh
        return nothing


def read_scans(path: PathLike, mesh_points: int = DEFAULT_MESH_POINTS) -> List[Tuple[str, np.ndarray]]:
    """The scans of a file as (name, (N, 3) float64 points): every scan of an E57, in the file's
    common frame (each scan's pose applied, where it has one), named ``FILE#INDEX`` when the file
    holds several; any other file is one scan (:func:`read_points`), named by its path.

    Raises:
        UsageError: missing file or unknown extension.
        InputError: an E57 without scans, or a scan without Cartesian coordinates or points.
    """
    path = Path(path)
    check_extension(path, READ_EXTENSIONS, "a point cloud")
    check_readable(path)
    if path.suffix.lower() != ".e57":
        return [(str(path), read_points(path, mesh_points=mesh_points))]
    import pye57

    try:
        e57 = pye57.E57(str(path))
    except Exception as e:  # libE57's own exceptions, with long messages
        raise InputError(f"{path}: not a readable E57 file ({first_line(e)})") from None
    try:
        count = e57.scan_count
        if count == 0:
            raise InputError(f"{path}: holds no scan")
        scans = []
        for index in range(count):
            try:
                data = e57.read_scan(index, ignore_missing_fields=True)
            except Exception as e:
                raise InputError(f"{path}, scan {index}: cannot be read ({first_line(e)})") from None
            if "cartesianX" not in data:
                raise InputError(f"{path}, scan {index}: no Cartesian coordinates (cartesianX/Y/Z); spherical-only scans are not read")
            points = np.column_stack([data["cartesianX"], data["cartesianY"], data["cartesianZ"]]).astype(np.float64)
            if len(points) == 0:
                raise InputError(f"{path}, scan {index}: holds 0 points")
            scans.append((f"{path}#{index}" if count > 1 else str(path), points))
    finally:
        e57.close()
    return scans


def _read_las(path: Path) -> np.ndarray:
    import laspy

    try:
        las = laspy.read(str(path))
    except Exception as e:  # laspy raises LaspyException, or the LAZ backend's errors
        raise InputError(f"{path}: not a readable LAS/LAZ file ({first_line(e)})") from None
    if len(las.points) == 0:
        raise InputError(f"{path}: holds 0 points")
    return _las_xyz(las)


def _las_xyz(las) -> np.ndarray:
    """(N, 3) float64 coordinates of a laspy LasData (its scaled x, y, z)."""
    return np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)]).astype(np.float64)


def _write_las(f, points: np.ndarray, rgb: Optional[np.ndarray] = None) -> None:
    """LAS 1.4, coordinates stored as integers on :func:`_las_steps`: point format 0, or 2 with
    the (N, 3) uint8 colours `rgb` (stored 16-bit, as the format holds them: times 257)."""
    import laspy

    header = laspy.LasHeader(point_format=0 if rgb is None else 2, version="1.4")
    header.offsets, header.scales = _las_steps(points)
    las = laspy.LasData(header)
    las.x, las.y, las.z = points[:, 0], points[:, 1], points[:, 2]
    if rgb is not None:
        wide = rgb.astype(np.uint16) * np.uint16(257)
        las.red, las.green, las.blue = wide[:, 0], wide[:, 1], wide[:, 2]
    las.write(f)


def _write_las_moved(path: Path, source: Path, T: np.ndarray) -> Path:
    """The LAS/LAZ file `source` as LAS with its coordinates moved by the (4, 4) `T`, every other
    dimension kept, on :func:`_las_steps` (the source's step where finer)."""
    import laspy

    las = laspy.read(str(source))
    xyz = apply_transform(T, _las_xyz(las))
    offsets, scales = _las_steps(xyz, np.asarray(las.header.scales, dtype=np.float64))
    las.header.scales, las.header.offsets = scales, offsets  # the stored integers are all set anew below
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    with atomic_output(path) as tmp:
        las.write(str(tmp))
    return path


def _las_steps(points: np.ndarray, finer: Optional[np.ndarray] = None) -> Tuple[np.ndarray, np.ndarray]:
    """(3,) offsets and (3,) scales of a LAS file holding the (N, 3) `points` as integers: a step of
    :data:`LAS_RESOLUTION`, or a millionth of the cloud's extent where that is finer (a cloud in
    kilometres would otherwise round to a few points), or `finer`'s per axis where that is finer
    still; coarser only where the cloud spans more than 2^31 steps. The offsets: the lowest
    corner, rounded down to a power of ten near the extent."""
    if not len(points):
        return np.zeros(3), np.full(3, LAS_RESOLUTION)
    extent = float(np.max(np.ptp(points, axis=0)))
    near = 10.0 ** np.floor(np.log10(extent)) if extent > 0 else 1.0
    step = np.full(3, min(LAS_RESOLUTION, 1e-6 * near))
    if finer is not None:
        step = np.minimum(step, finer)
    offsets = np.floor(points.min(axis=0) / near) * near
    return offsets, np.maximum(step, (points.max(axis=0) - offsets) / (2**31 - 2))  # the stored integers are int32


def _read_npy_points(path: Path) -> np.ndarray:
    try:
        arr = np.load(path, allow_pickle=False)
    except Exception as e:  # numpy raises ValueError/OSError/EOFError for bad files
        raise InputError(f"{path}: not a readable .npy array ({e})") from None
    if arr.ndim != 2 or arr.shape[1] != 3 or not np.issubdtype(arr.dtype, np.number):
        raise InputError(f"{path}: expected a numeric array of shape (N, 3), got {arr.dtype} {arr.shape}")
    if len(arr) == 0:
        raise InputError(f"{path}: parsed to 0 points")
    return arr.astype(np.float64)


def make_folder(path: PathLike) -> Path:
    """Create the folder `path` (and its parents) unless it exists.

    Raises:
        InputError: it cannot be created (a file in the way, a read-only disk, no permission).
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise InputError(f"{path}: cannot create this folder, a file of that name exists")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise InputError(f"{path}: cannot create this folder ({e.strerror or e})") from None
    if not os.access(path, os.W_OK | os.X_OK):
        raise InputError(f"{path}: cannot write in this folder (permission denied)")
    return path


def check_writable(path: PathLike) -> None:
    """Raise InputError unless a file can be written at `path`: its folder exists, is writable
    and takes a new file; UsageError where `path` is a folder (checked before long work, so that
    it fails at once)."""
    folder = _output_folder(Path(path))
    try:  # what os.access does not tell: a folder that takes no new file (/proc, some mounts; any, for root)
        fd, probe = tempfile.mkstemp(prefix=".o3dsoft-check-", dir=folder)
    except OSError as e:
        raise InputError(f"{path}: cannot create a file in folder {folder} ({e.strerror or e})") from None
    os.close(fd)
    os.unlink(probe)


def _output_folder(path: Path) -> Path:
    """The folder of the output file `path`, checked: it exists and is writable, and `path` is
    not a folder (InputError, UsageError)."""
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise InputError(f"{path}: cannot write, folder {folder} does not exist")
    if path.is_dir():
        raise UsageError(f"{path}: cannot write, it is a folder")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise InputError(f"{path}: cannot write in folder {folder} (permission denied)")
    return folder


def check_outputs_apart(outputs: Dict[str, Optional[PathLike]], inputs: Dict[str, Optional[PathLike]]) -> None:
    """Raise UsageError where an output file (by option name, e.g. ``{"--out": path}``; None: not
    asked for) is one of the input files or another output: writing it would destroy the data
    read, or one output would replace another. Links and other spellings of a path count."""
    seen: Dict[str, Path] = {}
    for name, path in list(inputs.items()) + list(outputs.items()):
        if path is None:
            continue
        path = Path(path)
        for other, taken in seen.items():
            if name in outputs and _same_file(path, taken):
                raise UsageError(f"{path} ({name}): the same file as {other}; o3dsoft writes over neither what it reads nor another of its outputs")
        seen[name] = path


def _same_file(a: Path, b: Path) -> bool:
    if a.exists() and b.exists():
        return os.path.samefile(a, b)
    return a.resolve() == b.resolve()


def remove_stale_temporaries(folder: PathLike, names) -> List[Path]:
    """Delete the temporary files :func:`atomic_output` leaves beside the files `names` of
    `folder` when a process is killed outright (kill -9, a power cut) mid-write; returns them."""
    stale = []
    for name in names:
        prefix, suffix = _temporary_affixes(Path(name))
        stale += [p for p in Path(folder).glob(f"{prefix}*{suffix}") if p.is_file()]
    for p in stale:
        p.unlink()
    return stale


@contextmanager
def atomic_output(path: PathLike) -> Iterator[Path]:
    """Yield a temporary path beside `path`; rename it to `path` only if the block succeeds and
    the file reaches the disk.

    The temporary name keeps the extension, so writers that pick a format by extension work.
    Raises InputError (UsageError for a folder) if the file cannot be written there (the checks
    of :func:`check_writable`; its temporary file is the test that the folder takes one).
    """
    path = Path(path)
    folder = _output_folder(path)
    prefix, suffix = _temporary_affixes(path)
    try:
        fd, tmp_name = tempfile.mkstemp(prefix=prefix, suffix=suffix, dir=folder)
    except OSError as e:
        raise InputError(f"{path}: cannot create a file in folder {folder} ({e.strerror or e})") from None
    os.close(fd)
    tmp = Path(tmp_name)
    os.chmod(tmp, 0o666 & ~_umask())  # mkstemp creates 0600; give the file the usual mode
    try:
        yield tmp
        _sync(tmp)
        os.replace(tmp, path)
    except OSError as e:
        raise InputError(f"{path}: cannot write ({e.strerror or e})") from None
    finally:
        if tmp.exists():
            tmp.unlink()


def _temporary_affixes(path: Path) -> Tuple[str, str]:
    """The prefix and suffix of :func:`atomic_output`'s temporary names for `path`: hidden, and
    with the extension kept."""
    return f".{path.stem}.", path.suffix


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _colour_bytes(colors: np.ndarray) -> np.ndarray:
    """(N, 3) uint8 of colours in 0-1 (floats) or 0-255 (uint8, as images store them).

    Raises:
        ValueError: float colours above 1 (0-255 values given as floats: divide them by 255).
    """
    if colors.dtype == np.uint8:
        return colors
    colors = colors.astype(np.float64)
    if colors.size and np.nanmax(colors) > 1.0:
        raise ValueError(f"colors must be in 0-1 (or uint8 in 0-255), got values up to {np.nanmax(colors):g}: divide 0-255 colours by 255")
    return np.round(np.clip(colors, 0.0, 1.0) * 255).astype(np.uint8)


PCD_ROUNDING = 1e-6  # the share of a cloud's extent float32 may round its coordinates by in a PCD file


def pcd_needs_doubles(points: np.ndarray) -> bool:
    """Whether float32 would round the (N, 3) points by more than PCD_ROUNDING of their extent
    (clouds far from their frame's origin: at 5e6 m from it, float32 steps by 0.5 m), so that a
    PCD file of them holds float64 x, y, z. Open3D 0.20 reads those as zeros; PCL, CloudCompare
    and o3dsoft read them."""
    finite = points[np.isfinite(points).all(axis=1)]
    if len(finite) == 0:
        return False
    return _rounded_beyond_share(finite, float(np.abs(finite.astype(np.float32).astype(np.float64) - finite).max()))


def _rounded_beyond_share(finite: np.ndarray, rounding: float) -> bool:
    """Whether `rounding` (cloud units) exceeds ``PCD_ROUNDING`` of the extent of the (N, 3) finite points."""
    return rounding > PCD_ROUNDING * float(np.linalg.norm(finite.max(axis=0) - finite.min(axis=0)))


def stored_as_float32(path: PathLike) -> bool:
    """Whether the PLY or PCD file `path` stores its x, y, z as 4-byte floats (False for other
    formats, and where the header cannot be read: the reader reports that)."""
    path = Path(path)
    ext = path.suffix.lower()
    if ext == ".ply":
        header = _ply_header(path)
        types = _ply_vertex_types(header[1]) if header is not None else {}
        return all(types.get(c) == np.dtype(np.float32) for c in "xyz")
    if ext == ".pcd":
        found = _pcd_header(path)
        if found is None:
            return False
        fields = found[0]
        stored = {name: (t.upper(), z) for name, z, t in zip(fields.get("FIELDS", []), fields.get("SIZE", []), fields.get("TYPE", []))}
        return all(stored.get(c) == ("F", "4") for c in "xyz")
    return False


def float32_rounding(path: PathLike, points: np.ndarray) -> Optional[float]:
    """How far float32 may have rounded the (N, 3) `points` read from `path` (cloud units: half a
    float32 step at the largest coordinate), where the file stores them as float32 and that is
    more than ``PCD_ROUNDING`` of their extent, as :func:`pcd_needs_doubles` judges (clouds far from
    their frame's origin: 4e6 m out, float32 steps by 0.25 m); else None. The rounding happened
    when the file was written: nothing read from it can undo it."""
    if not stored_as_float32(path):
        return None
    finite = points[np.isfinite(points).all(axis=1)]
    if len(finite) == 0:
        return None
    rounding = float(np.spacing(np.float32(np.abs(finite).max()))) / 2.0
    return rounding if _rounded_beyond_share(finite, rounding) else None


def write_points(
    path: PathLike, points: np.ndarray, colors: Optional[np.ndarray] = None, normals: Optional[np.ndarray] = None, width: Optional[int] = None
) -> Path:
    """Write (N, 3) points to any of the point formats (by extension), atomically; with (N, 3)
    `colors` (0-1) and `normals` where the format holds them (colours: .ply, .pcd, .las, .pts;
    normals: .ply, .pcd, .xyzn), ignored elsewhere; `width`: a .pcd's points are rows of that
    many (an organised cloud, a range image's: HEIGHT N / width; None: one row), ignored elsewhere.

    The files are written here rather than by Open3D, whose writers report success after a
    failed write (a full disk left a truncated file): binary little-endian PLY of float64
    coordinates (normals float64, colours 8-bit), PCD of float32 (as Open3D writes them: its reader
    takes no other; colours packed in one 'rgb' field) unless float32 would move the points
    (:func:`pcd_needs_doubles`: then x, y, z are float64, as PCL writes them), and text with 10 decimals (.pts: the
    point count first, then "x y z r g b" rows with 8-bit colours where there are colours; .xyzn: the normals that format carries, estimated from 30 neighbours where
    none are given), and LAS 1.4 of point format 0 (2 with colours) at a 1e-4-unit step (0.1 mm for metres; coarser where the cloud spans more than 2^31 steps)."""
    path = Path(path)
    ext = check_extension(path, WRITE_EXTENSIONS, "writing points")
    points = np.ascontiguousarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {points.shape}")
    for name, values in (("colors", colors), ("normals", normals)):
        if values is not None and np.shape(values) != points.shape:
            raise ValueError(f"{name} must be (N, 3) as the points {points.shape}, got {np.shape(values)}")
    if width is not None and not (width >= 1 and len(points) % width == 0):
        raise ValueError(f"width must divide the {len(points)} points into rows, got {width}")
    rgb = None if colors is None else _colour_bytes(np.asarray(colors))
    with atomic_output(path) as tmp, open(tmp, "wb") as f:
        if ext == ".npy":
            np.save(f, points)
        elif ext == ".las":
            _write_las(f, points, rgb)
        elif ext == ".ply":
            fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
            fields += [] if normals is None else [("nx", "<f8"), ("ny", "<f8"), ("nz", "<f8")]
            fields += [] if rgb is None else [("red", "u1"), ("green", "u1"), ("blue", "u1")]
            rows = np.empty(len(points), dtype=fields)
            for k, name in enumerate("xyz"):
                rows[name] = points[:, k]
                if normals is not None:
                    rows[f"n{name}"] = normals[:, k]
            if rgb is not None:
                rows["red"], rows["green"], rows["blue"] = rgb.T
            kinds = {"<f8": "double", "u1": "uchar"}
            header = (
                f"ply\nformat binary_little_endian 1.0\nelement vertex {len(points)}\n"
                + "".join(f"property {kinds[t]} {n}\n" for n, t in fields)
                + "end_header\n"
            )
            f.write(header.encode("ascii") + rows.tobytes())
        elif ext == ".pcd":
            coordinate = "<f8" if pcd_needs_doubles(points) else "<f4"
            fields = [(c, coordinate) for c in "xyz"] + ([] if normals is None else [(f"normal_{c}", "<f4") for c in "xyz"])
            fields += [] if rgb is None else [("rgb", "<u4")]  # PCD's packed colour: 0x00RRGGBB read as a float32
            rows = np.empty(len(points), dtype=fields)
            for k, c in enumerate("xyz"):
                rows[c] = points[:, k]
                if normals is not None:
                    rows[f"normal_{c}"] = np.asarray(normals)[:, k]
            if rgb is not None:
                rows["rgb"] = (rgb[:, 0].astype(np.uint32) << 16) | (rgb[:, 1].astype(np.uint32) << 8) | rgb[:, 2].astype(np.uint32)
            n, k = len(points), len(fields)
            across, down = (n, 1) if width is None else (width, n // width)
            header = (
                f"# .PCD v0.7\nVERSION 0.7\nFIELDS {' '.join(name for name, _ in fields)}\nSIZE {' '.join(t[-1] for _, t in fields)}\n"
                f"TYPE {' '.join(['F'] * k)}\nCOUNT {' '.join(['1'] * k)}\nWIDTH {across}\nHEIGHT {down}\nVIEWPOINT 0 0 0 1 0 0 0\n"
                f"POINTS {n}\nDATA binary\n"
            )
            f.write(header.encode("ascii") + rows.tobytes())
        else:
            columns = points
            if ext == ".xyzn":
                if normals is None:
                    from .preprocess import local_origin

                    o3d = _o3d()
                    centred = points - local_origin(points)  # far from the origin (georeferenced), Open3D's float sums lose the surface
                    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(centred))
                    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(30))
                    normals = np.asarray(cloud.normals)
                columns = np.hstack([points, normals])
            fmt = ["%.10f"] * columns.shape[1]
            if ext == ".pts" and rgb is not None:
                columns, fmt = np.hstack([points, rgb]), fmt + ["%d"] * 3
            header = {".pts": str(len(points)), ".csv": "x,y,z"}.get(ext, "")
            np.savetxt(f, columns, fmt=fmt, delimiter="," if ext == ".csv" else " ", header=header, comments="")
    return path


class PointAttributes(NamedTuple):
    """Per-point attributes of a cloud file, row for row with :func:`read_points`: colors (N, 3)
    in 0-1 and normals (N, 3); None where the file holds none."""

    colors: Optional[np.ndarray] = None
    normals: Optional[np.ndarray] = None


def read_attributes(path: PathLike, count: int, scan: Optional[int] = None) -> PointAttributes:
    """The colours and normals of a point-cloud file Open3D reads (.ply without faces, .pcd,
    .xyzn, .xyzrgb, and Leica's .pts of "x y z intensity r g b"), and the colours of a LAS/LAZ file
    of a colour point format and of an E57 scan (`scan`: its index; None: the file's only one),
    where it holds `count` points as :func:`read_points` / :func:`read_scans` read them; none for
    other files (a mesh's points are sampled; tables carry none here)."""
    path = Path(path)
    ext = path.suffix.lower()
    if ext in (".las", ".laz"):
        return _las_colours(path, count)
    if ext == ".e57":
        return _e57_colours(path, count, scan)
    if ext not in (".ply", ".pcd", ".xyzn", ".xyzrgb", ".pts"):
        return PointAttributes()
    header = _ply_header(path) if ext == ".ply" else None
    if header is not None and not any(name == "face" and n > 0 for name, n, _ in header[1]):  # a mesh's points are sampled
        types = _ply_vertex_types(header[1])
        if _open3d_misreads_ply(header[1]) or any(c in types and types[c].kind == "f" for c in ("red", "green", "blue")):
            return _ply_attributes(path, header, count, types)
    o3d = _o3d()
    with _open3d_quietly():
        if ext == ".ply" and len(o3d.io.read_triangle_mesh(str(path)).triangles) > 0:
            return PointAttributes()
        cloud = o3d.io.read_point_cloud(str(path), format="auto")
    if len(cloud.points) != count:
        return PointAttributes()
    return PointAttributes(
        np.asarray(cloud.colors, dtype=np.float64) if cloud.has_colors() else None,
        np.asarray(cloud.normals, dtype=np.float64) if cloud.has_normals() else None,
    )


def _ply_attributes(path: Path, header: PlyHeader, count: int, types: Dict[str, np.dtype]) -> PointAttributes:
    """The colours and normals of the PLY `path` (its :func:`_ply_header`; its vertices' `types`)
    read here, where Open3D mixes up the points or scales float colours in 0-1 down by 255:
    colours stored as floats are taken as 0-1 where none exceeds 1, else over 255; integer ones
    over their type's largest value (:func:`_unit_colours`)."""
    columns = _ply_vertex_columns(path, header)
    if columns is None or len(columns["x"]) != count:
        return PointAttributes()
    colors = normals = None
    if all(c in columns for c in ("red", "green", "blue")):
        rgb = np.nan_to_num(np.stack([columns[c] for c in ("red", "green", "blue")], axis=1).astype(np.float64))
        kind = types["red"]
        limit = (1.0 if rgb.max(initial=0.0) <= 1.0 else 255.0) if kind.kind == "f" else float(np.iinfo(kind).max)
        colors = _unit_colours(rgb, limit)
    if all(n in columns for n in ("nx", "ny", "nz")):
        normals = np.stack([columns[n] for n in ("nx", "ny", "nz")], axis=1).astype(np.float64)
    return PointAttributes(colors, normals)


def _e57_colours(path: Path, count: int, scan: Optional[int]) -> PointAttributes:
    """An E57 scan's colorRed, colorGreen and colorBlue as (N, 3) colours in 0-1, over the file's
    colour limits (:func:`_unit_colours`)."""
    import pye57

    try:
        e57 = pye57.E57(str(path))
        try:
            if scan is None and e57.scan_count != 1:
                return PointAttributes()
            index = 0 if scan is None else scan
            data = e57.read_scan(index, colors=True, ignore_missing_fields=True)
            try:
                limit = float(e57.get_header(index).node["colorLimits"]["colorRedMaximum"].value())
            except Exception:  # no colour limits written
                limit = 0.0
        finally:
            e57.close()
    except Exception:  # unreadable here: read_scans says why where it matters
        return PointAttributes()
    if not {"colorRed", "colorGreen", "colorBlue"} <= set(data) or len(data["colorRed"]) != count:
        return PointAttributes()
    return PointAttributes(_unit_colours(np.column_stack([data["colorRed"], data["colorGreen"], data["colorBlue"]]), limit))


def _las_colours(path: Path, count: int) -> PointAttributes:
    """A LAS/LAZ file's red, green and blue as (N, 3) colours in 0-1: 16-bit values, or 8-bit ones
    where no value exceeds 255 (as some writers store them)."""
    import laspy

    las = laspy.read(str(path))
    if len(las.points) != count or not {"red", "green", "blue"} <= set(las.point_format.dimension_names):
        return PointAttributes()
    return PointAttributes(_unit_colours(np.column_stack([np.asarray(las.red), np.asarray(las.green), np.asarray(las.blue)])))


def _unit_colours(rgb: np.ndarray, limit: float = 0.0) -> np.ndarray:
    """(N, 3) integer colours as floats in 0-1, over `limit` (the file's largest value), or where
    it gives none, over 255 if no value exceeds it (8-bit, as some writers store 16-bit fields)
    and 65535 otherwise."""
    rgb = np.asarray(rgb, dtype=np.float64)
    if not limit > 0:
        limit = 255.0 if rgb.max(initial=0.0) <= 255.0 else 65535.0
    return np.clip(rgb / limit, 0.0, 1.0)


def write_moved(path: PathLike, source: PathLike, points: np.ndarray, T: np.ndarray) -> Path:
    """Write the (N, 3) `points` read from the file `source` (:func:`read_points`), moved by the
    (4, 4) rigid `T`, to `path` (any of :data:`WRITE_EXTENSIONS`), with what of the source's
    per-point attributes the output holds: a LAS/LAZ source written as .las keeps every dimension
    (intensity, returns, classification, GPS time, colour), its coordinates moved; colours
    (:func:`read_attributes`) go into .ply, .pcd, .las and .pts, and normals, turned by T, into
    .ply, .pcd and .xyzn; an organised PCD source (a range image's rows, its invalid points NaN)
    written as .pcd keeps its WIDTH and HEIGHT."""
    path, source = Path(path), Path(source)
    if path.suffix.lower() == ".las" and source.suffix.lower() in (".las", ".laz"):
        return _write_las_moved(path, source, T)
    colors, normals = read_attributes(source, len(points))
    return write_points(path, apply_transform(T, points), colors, None if normals is None else normals @ T[:3, :3].T, _pcd_width(path, source, len(points)))


def _pcd_width(path: Path, source: Path, count: int) -> Optional[int]:
    """The WIDTH of the organised PCD `source` (HEIGHT over 1) of `count` points where `path` is a
    .pcd too; else None (one row)."""
    if path.suffix.lower() != ".pcd" or source.suffix.lower() != ".pcd":
        return None
    found = _pcd_header(source)
    if found is None:
        return None
    width, height = (found[0].get(key, [""])[0] for key in ("WIDTH", "HEIGHT"))
    if width.isdigit() and height.isdigit() and int(height) > 1 and int(width) * int(height) == count:
        return int(width)
    return None


def _sync(path: Path) -> None:
    """Flush `path` to the disk, so that a write the disk could not hold fails here, before the
    rename, rather than later."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def read_transform(path: PathLike, about: Optional[np.ndarray] = None) -> np.ndarray:
    """Read a rigid 4x4 transform from text (whitespace/comma separated) or .npy.

    A 3x4 [R | t] text is accepted too (the last row is implied).

    Published ground truths are often rounded (3DMatch's are orthonormal to about 2e-4): a
    rotation block within 1e-3 of orthonormal is accepted and replaced by the nearest rotation
    (within :data:`EXACT_WITHIN`, as :func:`write_transform` writes them, kept to the bit),
    with the translation changed so that the transform still moves the point `about` (3,) where
    the file's does: pass the moved cloud's :func:`~o3dsoft.preprocess.local_origin`. (About the
    frame's origin, a rotation changed by 4e-7 moves a cloud 5e6 m away, georeferenced, by 2 m.)

    Raises:
        UsageError: missing file.
        InputError: names the line and what was wrong: non-numeric value, wrong shape, or not a
            rigid transform (R not orthonormal with det +1 within 1e-3, last row not 0 0 0 1).
    """
    path = Path(path)
    check_readable(path)
    if path.suffix.lower() == ".npy":
        try:
            T = np.load(path, allow_pickle=False)
        except Exception as e:
            raise InputError(f"{path}: not a readable .npy array ({e})") from None
        if not np.issubdtype(T.dtype, np.number):
            raise InputError(f"{path}: expected a numeric 4x4 array, got dtype {T.dtype}")
        T = T.astype(np.float64)
    else:
        T = _parse_matrix_text(path)
    if T.shape not in ((3, 4), (4, 4)):
        raise InputError(f"{path}: expected a 4x4 transform (or 3x4 [R|t]), got shape {T.shape}")
    return _rigid_as_read(T, str(path), about)


def _with_last_row(T: np.ndarray) -> np.ndarray:
    """A (3, 4) [R | t] as a (4, 4) transform with the last row 0 0 0 1; other shapes copied as
    they are."""
    return np.vstack([T[:3], [0.0, 0.0, 0.0, 1.0]]) if T.shape == (3, 4) else T.copy()


# A rotation read whose R R^T is this close to I is taken as written: float64 products of
# rotations are orthonormal to about 1e-15; a text of 9 digits to about 1e-9.
EXACT_WITHIN = 1e-12


def _rigid_as_read(T: np.ndarray, where: str, about: Optional[np.ndarray] = None) -> np.ndarray:
    """The (4, 4) transform read at `where` ((3, 4) [R | t] or (4, 4)), checked rigid within
    READ_TOLERANCE, with the nearest rotation where it is further than :data:`EXACT_WITHIN` from
    orthonormal (so that the stricter checks downstream hold; nearer, kept, so that what
    :func:`write_transform` wrote reads back bit for bit) and an exact last row; the translation
    keeps where the point `about` (3,) goes (None: the origin)."""
    T = _with_last_row(T)
    check_rigid(T, where, tol=READ_TOLERANCE)
    return nearest_rigid(T, about, keep_within=EXACT_WITHIN)


def _parse_matrix_text(path: Path) -> np.ndarray:
    rows = [row for _, row in _number_lines(path, (4,), "4 lines of 4 numbers")]
    if not rows:
        raise InputError(f"{path}: empty; expected 4 lines of 4 numbers")
    return np.array(rows, dtype=np.float64)


def _number_lines(path: Path, counts: Tuple[int, ...], expected: str) -> List[Tuple[int, List[float]]]:
    """The (line number, numbers) of a text file's lines that hold any, each holding one of
    `counts` numbers (whitespace or comma separated; '#' starts a comment)."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a text file; expected {expected}") from None
    per_line = " or ".join(map(str, counts))
    rows = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        content = line.split("#", 1)[0].replace(",", " ").split()
        if not content:
            continue
        try:
            rows.append((lineno, [float(v) for v in content]))
        except ValueError:
            bad = next(v for v in content if not _is_float(v))
            raise InputError(f"{path}, line {lineno}: {bad!r} is not a number; expected {per_line} numbers per line") from None
        if len(rows[-1][1]) not in counts:
            raise InputError(f"{path}, line {lineno}: {len(rows[-1][1])} values; expected {per_line} per line")
    return rows


def read_poses(path: PathLike, names: Sequence[str], about: Optional[Sequence[np.ndarray]] = None, what: str = "scans") -> List[Optional[np.ndarray]]:
    """Initial poses (4, 4) world_T_scan of the scans `names`, None where the file has none
    (`what`: what the clouds are called in messages, plural).

    Three layouts:
        ``.json``: ``{"scans": [{"name": ..., "world_T_scan": 4x4 or null}, ...]}``, the
            poses.json that ``o3dsoft multiway`` writes, or ``{"sweeps": [{"name": ...,
            "world_T_sweep": 4x4}, ...]}``, that of ``o3dsoft odometry``; a scan is found by its
            name, else by its file name.
        ``.conf``: the Stanford 3D Scanning Repository's ``bmesh NAME tx ty tz qx qy qz qw``
            lines (:func:`o3dsoft.scans.read_conf`), found by name as a poses.json's.
        text (any other extension): one pose per line in the scans' order, 12 numbers (a 3x4
            [R | t] row by row, as KITTI's pose files) or 16 (4x4 row by row).
    Rotations within 1e-3 of orthonormal are replaced by the nearest rotation (kept within
    :data:`EXACT_WITHIN`), as :func:`read_transform` does, each pose keeping where it moves its scan's point in `about`
    (one (3,) point per scan, e.g. its :func:`~o3dsoft.preprocess.local_origin`; None: the origin).

    Raises:
        UsageError: missing file.
        InputError: names the line or scan and what was wrong.
    """
    path = Path(path)
    check_readable(path)
    if path.suffix.lower() == ".json":
        found = _poses_by_name(path, _json_entries(path), names)
    elif path.suffix.lower() == ".conf":
        from .scans import read_conf  # a Stanford 3D Scanning Repository's poses

        found = _poses_by_name(path, [{"name": name, "world_T_scan": T} for name, T in read_conf(path).items()], names)
    else:
        lines = _number_lines(path, (12, 16), "one pose per line, 12 or 16 numbers")
        if len(lines) != len(names):
            raise InputError(f"{path}: {len(lines)} poses for {len(names)} {what}; expected one line per {what[:-1]}, in the order the {what} are given")
        found = {k: (f"{path}, line {lineno}", np.array(row, dtype=np.float64).reshape(-1, 4)) for k, (lineno, row) in enumerate(lines)}
    poses: List[Optional[np.ndarray]] = [None] * len(names)
    for k, (where, T) in found.items():
        poses[k] = _rigid_as_read(T, where, None if about is None else about[k])
    return poses


def _json_entries(path: Path) -> List[dict]:
    """The entries {"name": ..., "world_T_scan": ...} of a poses.json (multiway's, or odometry's
    "sweeps")."""
    try:
        record = json.loads(path.read_text(encoding="utf-8-sig"))
    except (UnicodeDecodeError, ValueError, RecursionError) as e:
        raise InputError(f"{path}: not a JSON file ({first_line(e)}); expected o3dsoft multiway's poses.json") from None
    if isinstance(record, dict) and "scans" not in record and isinstance(record.get("sweeps"), list):  # o3dsoft odometry's
        record = {"scans": [{**e, "world_T_scan": e.get("world_T_sweep")} if isinstance(e, dict) else e for e in record["sweeps"]]}
    entries = record.get("scans") if isinstance(record, dict) else None
    if not isinstance(entries, list) or not all(isinstance(e, dict) and isinstance(e.get("name"), str) for e in entries):
        raise InputError(
            f'{path}: expected {{"scans": [{{"name": ..., "world_T_scan": ...}}, ...]}}, as o3dsoft multiway writes, '
            f'or {{"sweeps": [{{"name": ..., "world_T_sweep": ...}}, ...]}}, as o3dsoft odometry writes'
        )
    return entries


def _poses_by_name(path: Path, entries: List[dict], names: Sequence[str]) -> Dict[int, Tuple[str, np.ndarray]]:
    """{index of the scan in `names`: (where, (4, 4) pose)} from the `entries` {"name": ...,
    "world_T_scan": ...} of the file at `path`: each entry with a pose goes to the scan of its
    name, else to the one scan of its file name that no entry named."""
    entries = [e for e in entries if e.get("world_T_scan") is not None]
    index = {name: k for k, name in enumerate(names)}
    exact = [e for e in entries if e["name"] in index]
    unnamed: Dict[str, List[int]] = {}  # file name: the scans no entry names exactly
    for k, name in enumerate(names):
        if not any(e["name"] == name for e in exact):
            unnamed.setdefault(Path(name).name, []).append(k)
    target: Dict[int, dict] = {}
    for entry in exact:  # exact names first
        _claim(path, target, index[entry["name"]], entry, names)
    for entry in entries:  # then file names, among the scans no entry named
        if entry["name"] in index:
            continue
        same = unnamed.get(Path(entry["name"]).name, [])
        if len(same) > 1:
            raise InputError(
                f"{path}: scan {entry['name']!r} matches {len(same)} of the scans given by file name ({', '.join(names[k] for k in same)}); name them as the file does"
            )
        if same:
            _claim(path, target, same[0], entry, names)
    if not target:
        raise InputError(f"{path}: none of its scans with a pose is among the scans given (matched by name, then by file name)")
    found: Dict[int, Tuple[str, np.ndarray]] = {}
    for k, entry in target.items():
        where = f"{path}, scan {entry['name']!r}"
        try:
            T = np.array(entry["world_T_scan"], dtype=np.float64)
        except (TypeError, ValueError, OverflowError):
            raise InputError(f"{where}: world_T_scan is not a 4x4 array of numbers") from None
        if T.shape != (4, 4):
            raise InputError(f"{where}: world_T_scan has shape {T.shape}; expected 4x4")
        found[k] = (where, T)
    return found


def _claim(path: Path, target: Dict[int, dict], k: int, entry: dict, names: Sequence[str]) -> None:
    """Give scan `k` the pose of `entry`, unless another entry already gave it one."""
    if k in target:
        raise InputError(f"{path}: scans {target[k]['name']!r} and {entry['name']!r} both give the pose of {names[k]}")
    target[k] = entry


def _is_float(v: str) -> bool:
    try:
        float(v)
        return True
    except ValueError:
        return False


def host_array(value):
    """A torch tensor (on any device, with a gradient, in bfloat16) or an Open3D tensor
    (``open3d.core.Tensor``) as a NumPy array; anything else as it is."""
    if hasattr(value, "detach") and hasattr(value, "cpu"):  # torch
        value = value.detach().cpu()
        return (value.double() if value.is_floating_point() else value).numpy()  # NumPy has no bfloat16
    if type(value).__module__.startswith("open3d") and hasattr(value, "numpy") and hasattr(value, "cpu"):
        return value.cpu().numpy()
    return value


def as_rigid(T, name: str) -> np.ndarray:
    """`T` as a (4, 4) float64 array; InputError naming `name` unless it is a finite rigid 4x4
    transform (:func:`check_rigid`). A torch or Open3D tensor is taken as its values."""
    if isinstance(T, (str, os.PathLike)):
        raise InputError(f"{name}: expected a 4x4 transform, got the file name {str(T)!r} (read it with o3dsoft.read_transform)")
    try:
        T = np.asarray(host_array(T), dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected a 4x4 transform of numbers, got {type(T).__name__}") from None
    T = _with_last_row(T)  # a 3x4 [R | t], as transform files may hold it
    if T.shape != (4, 4):
        raise InputError(f"{name}: expected a 4x4 transform (or 3x4 [R | t]), got shape {T.shape}")
    check_rigid(T, name)
    return T


def check_rigid(T: np.ndarray, name: str = "transform", tol: float = 1e-4) -> None:
    """Raise InputError unless T is a finite rigid 4x4 transform (rotation + translation)."""
    if not np.isfinite(T).all():
        raise InputError(f"{name}: contains NaN or inf")
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=tol):
        raise InputError(f"{name}: last row is {T[3].tolist()}, expected [0, 0, 0, 1]")
    R = T[:3, :3]
    err = np.abs(R.T @ R - np.eye(3)).max()
    if err > tol:
        raise InputError(f"{name}: not a rigid transform; the 3x3 block is not orthonormal (|R^T R - I| = {err:.2g})")
    if np.linalg.det(R) < 0:
        raise InputError(f"{name}: not a rigid transform; the 3x3 block is a reflection (det = -1)")


def write_transform(path: PathLike, T: np.ndarray) -> Path:
    """Write a rigid 4x4 transform as text (any extension but .npy; 17 significant digits, which
    read back to the same float64) or .npy, atomically.

    Raises:
        InputError: `T` is not a finite rigid 4x4 transform (within :data:`READ_TOLERANCE`, what
            :func:`read_transform` reads back).
    """
    path = Path(path)
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise InputError(f"{path}: a transform to write must be 4x4, got shape {T.shape}")
    check_rigid(T, str(path), tol=READ_TOLERANCE)
    with atomic_output(path) as tmp:
        if path.suffix.lower() == ".npy":
            with open(tmp, "wb") as f:
                np.save(f, np.asarray(T, dtype=np.float64))
        else:
            np.savetxt(tmp, np.asarray(T, dtype=np.float64), fmt="%.17g")  # every bit: 1e-10 of a rotation moves a point 4e6 m out by 0.4 mm
    return path
