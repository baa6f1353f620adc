"""How long `o3dsoft --help`, `--version` and a subcommand's --help take, as a user runs them.

    python -m benchmarks.cli_startup [--rounds 7]

Runs each command in a fresh process `--rounds` times (after one untimed run that warms the file
cache) and prints the median wall time in seconds (lower is better), with the time of a bare
`python -c pass` measured in the same run for comparison.
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import subprocess
import sys
import time

COMMANDS = (["--help"], ["--version"], ["register", "--help"], ["bench", "modelnet40", "--help"])


def median_seconds(argv: list, rounds: int) -> float:
    subprocess.run(argv, capture_output=True, check=True)
    times = []
    for _ in range(rounds):
        t0 = time.perf_counter()
        subprocess.run(argv, capture_output=True, check=True)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=7)
    args = ap.parse_args()
    exe = shutil.which("o3dsoft") or sys.exit("o3dsoft is not on PATH: install the package first")
    print(f"python -c pass: {median_seconds([sys.executable, '-c', 'pass'], args.rounds):.3f} s (median of {args.rounds}, lower is better)")
    for command in COMMANDS:
        print(f"o3dsoft {' '.join(command)}: {median_seconds([exe, *command], args.rounds):.3f} s")


if __name__ == "__main__":
    main()
