"""The library's benchmarks, one module per room they time (tools/bench_*.py and tools/benchmark.py run
them): sparse (detbench.sparse and voxelization), points (the point ops of detbench.ops), sim (the simulator), eval
(the evaluator), detectors (a built detector's latency, memory and size; the caller builds it). Each takes
its inputs and settings, returns the results dict the command writes as JSON, and renders it as Markdown.
The measuring primitives (timers, busy load) are detbench.utils.bench.

This package is the top layer of the library, above train: no library module imports it.
"""
