"""Per-scan time of Segmenter.segment from Python against the Rust time, in one run.

For each scan (loaded once with numpy): --warmup untimed calls, then --repeat timed calls of
a single-frame Segmenter; reports the median wall time of the Python call, the median of the
library's own fit + query time for the same calls (Segmenter.last_report), and, when --rust
names the `time-scans` binary, its median for the same scans (the whole Rust call, input
check included) run just before. Overhead = Python call / Rust call - 1.

    python crates/groundwork-py/bench.py --rust target/release/time-scans tests/data/semantickitti-00/velodyne/*.bin
"""
import argparse
import json
import statistics
import subprocess
import time

import numpy as np

import groundwork


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=20)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--rust", help="the time-scans binary, run on the same scans first")
    ap.add_argument("scans", nargs="+")
    a = ap.parse_args()
    rust = None
    if a.rust:
        out = subprocess.run(
            [a.rust, "--repeat", str(a.repeat), "--warmup", str(a.warmup), *a.scans],
            check=True, capture_output=True, text=True,
        ).stdout
        rust = json.loads(out)["median_ms"]
    wall, lib = [], []
    seg = groundwork.Segmenter(frames=1)
    for path in a.scans:
        points = np.fromfile(path, dtype=np.float32).reshape(-1, 4)
        for _ in range(a.warmup):
            seg.segment(points)
        for _ in range(a.repeat):
            t = time.perf_counter()
            seg.segment(points)
            wall.append((time.perf_counter() - t) * 1e3)
            r = seg.last_report
            lib.append(r["fit_ms"] + r["query_ms"])
    py, own = statistics.median(wall), statistics.median(lib)
    result = {
        "scans": len(a.scans),
        "python_call_ms": py,
        "library_fit_query_ms": own,
        "overhead_vs_fit_query": py / own - 1.0,
    }
    if rust is not None:
        result["rust_call_ms"] = rust
        result["overhead_vs_rust_call"] = py / rust - 1.0
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
