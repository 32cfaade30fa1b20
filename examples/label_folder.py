"""Label a folder of scans with TerraSeg's PseudoLabeler from Python, one scan per process.

    python examples/label_folder.py tests/data/semantickitti-00/velodyne labels/ --workers 2

Writes ``<out>/<scan>.prob`` (float32 ground probability per point, little-endian) and
``<out>/<scan>.ground`` (one byte per point, 1 = ground), the files ``groundwork label``
writes, with the same values for the same seed. Each file is written under a temporary name
and renamed, ``.ground`` last, so a rerun after a kill skips the scans that are complete and
redoes the rest. ``--shard i/n`` keeps every n-th scan of the sorted list, as ``label
--shard`` does, for several machines. docs/offline-labels.md.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np

import groundwork

SCAN_SUFFIXES = (".bin", ".pcd", ".ply")


def write_atomic(path: Path, data: bytes) -> None:
    tmp = path.with_name(path.name + ".partial")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def one_thread() -> None:
    # Read by the Rust thread pool when a worker first labels a scan.
    os.environ["RAYON_NUM_THREADS"] = "1"


def label_one(scan: Path, out: Path, seed: int, sensor: str | None) -> tuple[str, int, float]:
    """Labels one scan in this worker process: (name, points, ground fraction)."""
    points = groundwork.read_scan(scan)
    probs = groundwork.pseudo_label(points, seed=seed, sensor=sensor)
    stem = scan.name.split(".")[0]
    write_atomic(out / f"{stem}.prob", probs.astype("<f4").tobytes())
    write_atomic(out / f"{stem}.ground", (probs >= 0.5).astype(np.uint8).tobytes())
    return scan.name, len(probs), float(np.mean(probs >= 0.5)) if len(probs) else 0.0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scans", type=Path, help="folder of scans")
    ap.add_argument("out", type=Path, help="output folder")
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--sensor", default=None, help="preset (default: hdl64e)")
    ap.add_argument("--shard", default="0/1", help="i/n: every n-th scan from the i-th")
    args = ap.parse_args()
    i, n = (int(v) for v in args.shard.split("/"))
    if not 0 <= i < n:
        ap.error(f"--shard {args.shard}: need 0 <= i < n")
    scans = sorted(p for p in args.scans.iterdir() if p.name.endswith(SCAN_SUFFIXES))[i::n]
    args.out.mkdir(parents=True, exist_ok=True)
    todo = [s for s in scans if not (args.out / f"{s.name.split('.')[0]}.ground").exists()]
    print(f"{len(scans)} scans, {len(scans) - len(todo)} already complete", file=sys.stderr)
    failed = 0
    start = time.monotonic()
    # One scan per worker process and one thread per worker, as `groundwork label` does: the
    # labels do not depend on the thread count, and scans in parallel use the cores better
    # than threads inside one scan.
    with ProcessPoolExecutor(max_workers=args.workers, initializer=one_thread) as pool:
        jobs = {pool.submit(label_one, s, args.out, args.seed, args.sensor): s for s in todo}
        for k, job in enumerate(as_completed(jobs), 1):
            try:
                name, points, ground = job.result()
                print(f"[{k}/{len(todo)}] {name}: {points} points, {ground:.1%} ground",
                      file=sys.stderr)
            except Exception as e:  # a bad scan is reported and skipped, as `label` does
                failed += 1
                print(f"[{k}/{len(todo)}] {jobs[job].name}: {e}", file=sys.stderr)
    rate = len(todo) / max(time.monotonic() - start, 1e-9)
    print(f"{len(todo) - failed} labelled, {failed} failed, {rate:.2f} scans/s", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
