"""Real scans with reference poses, and what counts as success on them.

Two ways a folder lists its pairs:

- a Stanford ``.conf``: a line ``bmesh NAME tx ty tz qx qy qz qw`` places scan NAME in a common
  world frame, p_world = R(q)^T p_scan + t, with R(q) the rotation of the unit quaternion
  (qx, qy, qz, qw); other lines (``camera``...) are ignored;
- a ``pairs.txt``: one pair per line, ``source target transform`` (paths relative to the folder,
  the transform a 4x4 text T_target_source as :func:`o3dsoft.io.read_transform` reads; ``#``
  starts a comment).

A scan's *kind* (RGB-D fragment, LiDAR scene, object) sets the thresholds of success that its
field uses (:data:`KINDS`).
"""

from __future__ import annotations

import shlex
from pathlib import Path
from typing import Dict, List, NamedTuple, Tuple, Union

import numpy as np

from .errors import InputError, UsageError
from .transforms import quaternion_to_matrix, rigid


class Kind(NamedTuple):
    """The success thresholds of one kind of scan.

    recall: (degrees, distance) pairs, tightest first (the last is the test of success); a distance is in the scans' units (metres),
        or a share of the scene's size when ``relative``.
    about: what the kind is, in words.
    """

    recall: Tuple[Tuple[float, float], ...]
    relative: bool
    about: str


# The field's usual tests: for RGB-D a tight one and 3DMatch's registration recall (15 deg / 0.3 m);
# for LiDAR a fine one and KITTI's (5 deg / 2 m); for objects 1 deg / 1 % of the size and 5 / 5 %.
KINDS: Dict[str, Kind] = {
    "rgbd": Kind(((2.0, 0.05), (15.0, 0.3)), False, "indoor RGB-D fragments, metres"),
    "lidar": Kind(((1.0, 0.3), (5.0, 2.0)), False, "outdoor LiDAR scans, metres"),
    "object": Kind(((1.0, 0.01), (5.0, 0.05)), True, "object scans (structured light, turntable), any unit"),
}


# Metres per scan unit, by the unit's name (``bench scans --unit``).
UNITS: Dict[str, float] = {"m": 1.0, "cm": 0.01, "mm": 0.001}


def guess_kind(size: float) -> str:
    """The kind of a scan from its :func:`~o3dsoft.preprocess.scene_size` in metres: under 1 m an
    object, under 30 m an indoor RGB-D scene, else an outdoor LiDAR scene."""
    return "object" if size < 1.0 else "rgbd" if size < 30.0 else "lidar"


def recall_thresholds(kind: str, size: float, metres: float = 1.0) -> Tuple[Tuple[float, float], ...]:
    """(degrees, distance in cloud units) of `kind`'s tests, for scans of the given size (cloud
    units) whose unit is `metres` metres (the kinds' distances in metres become cloud units)."""
    if kind not in KINDS:
        raise UsageError(f"unknown scan kind {kind!r}; valid: {', '.join(KINDS)}")
    k = KINDS[kind]
    return tuple((deg, dist * size if k.relative else dist / metres) for deg, dist in k.recall)


class PairEntry(NamedTuple):
    """One line of a ``pairs.txt``: the two scans and the file of T_target_source."""

    source: Path
    target: Path
    transform: Path
    line: int


def check_pairs_file(path: Path) -> None:
    """UsageError unless `path` is a file (a pairs file of ``register --pairs`` or the bench)."""
    if path.is_dir():
        raise UsageError(f"{path}: is a folder; expected a pairs file")
    if not path.is_file():
        raise UsageError(f"{path}: no such pairs file")


def pair_lines(path: Union[str, Path], counts: Tuple[int, ...] = (3,), options: Tuple[str, ...] = ()) -> List[Tuple[int, List[Path], Dict[str, Path]]]:
    """(line number, files, named files) of each pair a pairs file lists: lines of `counts` file
    names (``source target transform``; ``#`` starts a comment; a name with spaces in quotes),
    and of any of `options` as ``name=file`` (e.g. ``init=guess.txt``), resolved against the
    file's folder.

    Raises:
        UsageError: no such file.
        InputError: a line with another number of fields (names the line); no pair at all.
    """
    path = Path(path)
    check_pairs_file(path)
    expected = "source target transform" if counts == (3,) else "source target [transform]"
    expected += "".join(f" [{name}=transform]" for name in options)
    lines = []
    for lineno, line in enumerate(path.read_text(encoding="utf-8-sig").splitlines(), start=1):
        files, named = [], {}
        for field in _fields(line, f"{path}, line {lineno}"):
            key, sep, value = field.partition("=")
            if sep and key in options:
                named[key] = path.parent / value
            else:
                files.append(path.parent / field)
        if not files and not named:
            continue
        if len(files) not in counts:
            raise InputError(f"{path}, line {lineno}: expected '{expected}', got {len(files)} field(s) (a file name with spaces goes in quotes)")
        lines.append((lineno, files, named))
    if not lines:
        raise InputError(f"{path}: no pairs (expected lines '{expected}')")
    return lines


def _fields(line: str, where: str) -> List[str]:
    """The names on a line of a pairs file: split at spaces, but a name may be quoted (shell
    rules; only lines with a quote are read so, so that Windows paths keep their backslashes)."""
    if '"' not in line and "'" not in line:
        return line.split("#", 1)[0].split()
    try:
        return shlex.split(line, comments=True)
    except ValueError as e:  # an unclosed quote
        raise InputError(f"{where}: {e}") from None


def read_pairs_file(path: Union[str, Path]) -> List[PairEntry]:
    """The pairs a ``pairs.txt`` lists, with paths resolved against its folder.

    Raises:
        UsageError: no such file.
        InputError: a line without three fields, or naming a file that does not exist (names the
            line); no pair at all.
    """
    path = Path(path)
    entries = []
    for lineno, files, _ in pair_lines(path):
        for f in files:
            if not f.is_file():
                raise InputError(f"{path}, line {lineno}: no file {f}")
        entries.append(PairEntry(*files, lineno))
    return entries


# What a pose line of a .conf holds, for the messages that refuse one.
_CONF_LINE = "'bmesh NAME tx ty tz qx qy qz qw'"


def read_conf(path: Union[str, Path]) -> Dict[str, np.ndarray]:
    """Scan name -> (4, 4) T_world_scan from a ``.conf`` file.

    Raises:
        InputError: a ``bmesh`` line without 7 finite numbers after the name, a quaternion of
            length 0, or a scan given twice (names the line).
    """
    path = Path(path)
    poses: Dict[str, np.ndarray] = {}
    lines: Dict[str, int] = {}  # the line of each scan's pose
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a text file; expected lines {_CONF_LINE}") from None
    for lineno, line in enumerate(text.splitlines(), start=1):
        parts = line.split()
        if not parts or parts[0] != "bmesh":
            continue
        if len(parts) != 9:
            raise InputError(f"{path}, line {lineno}: expected {_CONF_LINE}, got {len(parts)} fields")
        values = []
        for value in parts[2:]:
            try:
                values.append(float(value))
            except ValueError:
                raise InputError(f"{path}, line {lineno}: {value!r} is not a number; expected {_CONF_LINE}") from None
        tx, ty, tz, qx, qy, qz, qw = values
        if not all(np.isfinite([tx, ty, tz, qx, qy, qz, qw])) or np.linalg.norm([qx, qy, qz, qw]) == 0:
            raise InputError(f"{path}, line {lineno}: expected finite numbers and a quaternion of non-zero length, got {' '.join(parts[2:])}")
        if parts[1] in lines:
            raise InputError(f"{path}, line {lineno}: {parts[1]} has a pose at line {lines[parts[1]]} already")
        lines[parts[1]] = lineno
        poses[parts[1]] = rigid(quaternion_to_matrix(qx, qy, qz, qw).T, np.array([tx, ty, tz]))
    if not poses:
        raise InputError(f"{path}: no 'bmesh' lines; expected lines {_CONF_LINE}")
    return poses


def relative_pose(poses: Dict[str, np.ndarray], source: str, target: str) -> np.ndarray:
    """T_target_source = T_world_target^-1 T_world_source, (4, 4)."""
    return np.linalg.inv(poses[target]) @ poses[source]
