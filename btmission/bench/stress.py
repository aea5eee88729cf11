"""CPU-burning processes that load the machine while a benchmark (or a test) measures
(``btmission bench mavlink --stress N``).

The failures of issue #36 happened on a busy machine: a ground station's computer is never idle.
:func:`cpu_burners` starts ``n`` processes that spin on one CPU each and ends them — by their
process ids, each one it started and no other — when the ``with`` block ends, however it ends.
"""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager

MAX_BURNERS = 64

_SPIN = "while True: pass"


@contextmanager
def cpu_burners(n: int) -> Iterator[list[int]]:
    """``n`` processes spinning on the CPU while the block runs; yields their process ids."""
    if not 0 <= n <= MAX_BURNERS:
        raise ValueError(f"CPU burners must be 0-{MAX_BURNERS}, got {n}")
    procs: list[subprocess.Popen[bytes]] = []
    try:
        for _ in range(n):
            procs.append(
                subprocess.Popen(
                    [sys.executable, "-S", "-c", _SPIN],
                    stdin=subprocess.DEVNULL,
                    stdout=subprocess.DEVNULL,
                    stderr=subprocess.DEVNULL,
                )
            )
        yield [p.pid for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.terminate()
        for p in procs:
            try:
                p.wait(timeout=5)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
