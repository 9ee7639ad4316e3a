"""Measuring helpers shared by the benchmarks (tools/bench_*.py): timed repeats and achieved GFLOP/s."""
from __future__ import annotations

import statistics
import time
from typing import Callable


def timed(fn: Callable[[], object], repeats: int, sync: Callable[[], None]) -> dict:
    """Run ``fn`` once to warm up, then ``repeats`` times; milliseconds (median, best).

    ``sync`` is called after each run (e.g. ``torch.cuda.synchronize``; a no-op on CPU) so
    asynchronous work is inside the measured time."""
    fn()
    sync()
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        sync()
        ts.append((time.perf_counter() - t0) * 1e3)
    return {"ms": statistics.median(ts), "ms_best": min(ts)}


def gflops(pairs: int, cin: int, cout: int, ms: float) -> float:
    """Useful GFLOP/s: 2 FLOP per multiply-add, pairs * cin * cout multiply-adds."""
    return 2.0 * pairs * cin * cout / (ms * 1e-3) / 1e9 if ms > 0 else float("nan")


__all__ = ["timed", "gflops"]
