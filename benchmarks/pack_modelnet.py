"""A compact copy of ModelNet40 for the GPU machine, whose transfers hold at most 64 MiB.

    python -m benchmarks.pack_modelnet [--data ../shared/data/modelnet40_ply_hdf5_1024]
        [--out .carry/modelnet40_f16] [--test-shapes 400] [--train-shapes N]

Writes the official HDF5 layout (``ply_data_train0.h5``, ``ply_data_test0.h5``,
``shape_names.txt``) that ``o3dsoft.data`` reads: every training shape (or the first
``--train-shapes``), the first
``--test-shapes`` test shapes (the per-epoch evaluation), coordinates as float16 (at most 2.4e-4
off on radius-1 shapes, a two-hundredth of the 1,024-point spacing) with gzip. The full 1,024-point
training split comes to about 53 MB.
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path
from typing import Optional

import numpy as np

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "modelnet40_ply_hdf5_1024"


def read_split(root: Path, split: str):
    import h5py

    data, label = [], []
    for f in sorted(root.glob(f"ply_data_{split}*.h5")):
        with h5py.File(f, "r") as h5:
            data.append(np.asarray(h5["data"]))
            label.append(np.asarray(h5["label"]))
    return np.concatenate(data), np.concatenate(label)


def write_split(path: Path, data: np.ndarray, label: np.ndarray) -> None:
    import h5py

    with h5py.File(path, "w") as h5:
        h5.create_dataset("data", data=data.astype(np.float16), compression="gzip", compression_opts=9, shuffle=True)
        h5.create_dataset("label", data=label)


def pack(data: Path, out: Path, test_shapes: int = 400, train_shapes: Optional[int] = None) -> float:
    """Write the compact copy of the ModelNet40 folder `data` into `out` (the first
    `train_shapes` training shapes, None: all); returns its size in MiB."""
    out.mkdir(parents=True, exist_ok=True)
    points, label = read_split(data, "train")
    write_split(out / "ply_data_train0.h5", points[:train_shapes], label[:train_shapes])
    points, label = read_split(data, "test")
    write_split(out / "ply_data_test0.h5", points[:test_shapes], label[:test_shapes])
    shutil.copy(data / "shape_names.txt", out / "shape_names.txt")
    return sum(f.stat().st_size for f in out.iterdir()) / 2**20


def _positive(text: str) -> int:
    n = int(text)
    if n < 1:
        raise argparse.ArgumentTypeError(f"expected a positive number of shapes, got {text}")
    return n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--out", type=Path, default=Path(".carry/modelnet40_f16"))
    ap.add_argument("--test-shapes", type=_positive, default=400)
    ap.add_argument("--train-shapes", type=_positive, default=None, help="only the first N training shapes (default: all)")
    args = ap.parse_args()
    print(f"{args.out}: {pack(args.data, args.out, args.test_shapes, args.train_shapes):.1f} MiB")


if __name__ == "__main__":
    main()
