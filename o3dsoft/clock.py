"""Wall time per pipeline stage."""

from __future__ import annotations

import time
from typing import Dict


class StageClock:
    """Wall time per stage in milliseconds, summed over the stage's runs: each :meth:`lap` charges
    the time since the previous lap to the named stage."""

    def __init__(self) -> None:
        self.timings_ms: Dict[str, float] = {}
        self._last = time.perf_counter()

    def lap(self, stage: str) -> None:
        now = time.perf_counter()
        self.timings_ms[stage] = self.timings_ms.get(stage, 0.0) + (now - self._last) * 1000.0
        self._last = now
