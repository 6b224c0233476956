"""Which camera clouds the recorder writes: all of a camera that sends little, one in N of
one that sends much (as rosbag2 users throttle a camera), so the recorder keeps up.

A 10 Hz camera of 30 000 points sends about 5 MB of clouds a second; a stereo camera's
organized 672 x 376 clouds at 30 Hz 240 MB, and compressing each for run.mcap took 18-27 ms
(lz4, zstd; ``python -m wavegrasp.ops.bench_pipeline``): most of a core, on a 2-core
machine that runs the whole pipeline.
"""

from __future__ import annotations

import math

#: Clouds written whole before the camera's rate and size are judged.
SAMPLE = 10


class CloudThinner:
    """Decides, cloud by cloud, whether to write it: one in ``every``, or (``every`` 0) as
    many as ``budget_mb_s`` megabytes of clouds a second allows, judged on the first
    :data:`SAMPLE` clouds (all written) from their sizes and stamps, so a lockstep run
    writes the same clouds every time."""

    def __init__(self, every: int, budget_mb_s: float) -> None:
        if every < 0 or budget_mb_s <= 0:
            raise ValueError(f"cloud_every must be >= 0 and the budget > 0, got {every} and "
                             f"{budget_mb_s}")
        self.every = every
        self.budget_mb_s = budget_mb_s
        self.count = 0
        self._first = 0 if every else SAMPLE  # the first cloud counted in ``every``
        self._sizes: list[int] = []
        self._stamps: list[int] = []
        self.rate_mb_s: float | None = None  # what the camera sends, once judged

    def keep(self, size_bytes: int, stamp_ns: int) -> bool:
        """Whether to write the next cloud, ``size_bytes`` long, stamped ``stamp_ns``."""
        i = self.count
        self.count += 1
        if not self.every:
            self._sizes.append(size_bytes)
            self._stamps.append(stamp_ns)
            if len(self._sizes) == SAMPLE:
                self.every = self._judge()
            return True
        return i >= self._first and (i - self._first) % self.every == 0

    def _judge(self) -> int:
        span_s = (max(self._stamps) - min(self._stamps)) * 1e-9
        if span_s <= 0:
            return 1
        self.rate_mb_s = sorted(self._sizes)[len(self._sizes) // 2] * (SAMPLE - 1) / span_s / 1e6
        return max(1, math.ceil(self.rate_mb_s / self.budget_mb_s))
