"""Real scans with ground-truth poses in the Stanford ``.conf`` format.

A line ``bmesh NAME tx ty tz qx qy qz qw`` places scan NAME in a common world frame:
p_world = R(q)^T p_scan + t, with R(q) the rotation of the unit quaternion (qx, qy, qz, qw).
Other lines (``camera``...) are ignored.
"""

from __future__ import annotations

from pathlib import Path
from typing import Dict, Union

import numpy as np

from .errors import InputError
from .transforms import quaternion_to_matrix, rigid


def read_conf(path: Union[str, Path]) -> Dict[str, np.ndarray]:
    """Scan name -> (4, 4) T_world_scan from a ``.conf`` file.

    Raises:
        InputError: a ``bmesh`` line without 7 numbers after the name (names the line).
    """
    path = Path(path)
    poses: Dict[str, np.ndarray] = {}
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        parts = line.split()
        if not parts or parts[0] != "bmesh":
            continue
        if len(parts) != 9:
            raise InputError(f"{path}, line {lineno}: expected 'bmesh NAME tx ty tz qx qy qz qw', got {len(parts)} fields")
        try:
            tx, ty, tz, qx, qy, qz, qw = (float(v) for v in parts[2:])
        except ValueError:
            raise InputError(f"{path}, line {lineno}: non-numeric pose values") from None
        poses[parts[1]] = rigid(quaternion_to_matrix(qx, qy, qz, qw).T, np.array([tx, ty, tz]))
    if not poses:
        raise InputError(f"{path}: no 'bmesh' lines")
    return poses


def relative_pose(poses: Dict[str, np.ndarray], source: str, target: str) -> np.ndarray:
    """T_target_source = T_world_target^-1 T_world_source, (4, 4)."""
    return np.linalg.inv(poses[target]) @ poses[source]
