"""``o3dsoft`` from the source tree, without installing it: for the GPU machine lent through the
``run`` tool, which has torch and h5py but neither Open3D nor o3dsoft (training needs no Open3D).

On that machine, from the repository root, with the packed data carried
(``python -m benchmarks.pack_modelnet`` writes ``.carry/modelnet40_f16``) and, to go on with a
run, its folder carried too::

    python3 benchmarks/device_train.py train --data .carry/modelnet40_f16 --device cuda \\
        --protocol incongruent-mix --batch-size 64 --workers 12 --max-minutes 8 --out $OUT/run

``--max-minutes`` ends the run inside the machine's time with a checkpoint and model.pt in
``$OUT/run``, which come back; ``train --out RUN --resume`` goes on from them later, here or there.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def main() -> None:
    sys.path.insert(0, str(REPO))
    # The commands live in cli/ and import as o3dsoft.cli once installed; load them under that name.
    # The shipped models in weights/ likewise import as o3dsoft.weights.
    for name, folder in (("o3dsoft.cli", "cli"), ("o3dsoft.weights", "weights")):
        spec = importlib.util.spec_from_file_location(name, REPO / folder / "__init__.py", submodule_search_locations=[str(REPO / folder)])
        assert spec is not None and spec.loader is not None
        package = importlib.util.module_from_spec(spec)
        sys.modules[name] = package
        spec.loader.exec_module(package)
    from o3dsoft.cli.main import main as o3dsoft_main

    o3dsoft_main()


if __name__ == "__main__":
    main()
