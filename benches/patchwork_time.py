"""Times Patchwork++ (pypatchworkpp) on KITTI scans and scores it on the labeled ones.

Each scan is loaded once, segmented --repeat times after --warmup untimed runs; prints JSON
with the median time per scan (wall, and the process's CPU time) and the pooled metrics on
scans that have a labels/<stem>.label beside velodyne/, in both protocols (the classes of
config/labels/semantickitti.toml): gmm (vegetation ignored) and terraseg (vegetation is
non-ground). A scan is scored on its last run: Patchwork++ adapts its thresholds from run
to run, so accuracy figures come from --repeat 1 --warmup 0 over the sequence in order
(benches/compare_methods.sh).
"""
import argparse
import json
import os
import statistics
import time

import numpy as np
import pypatchworkpp

GROUND = {40, 44, 48, 49, 60, 72}
VEGETATION = {70}
IGNORED = {0, 1}


def metrics(tp, fp, fn, tn):
    iou_g = 100.0 * tp / max(tp + fp + fn, 1)
    iou_n = 100.0 * tn / max(tn + fp + fn, 1)
    return {
        "precision": 100.0 * tp / max(tp + fp, 1),
        "recall": 100.0 * tp / max(tp + fn, 1),
        "iou_ground": iou_g,
        "iou_nonground": iou_n,
        "miou": (iou_g + iou_n) / 2.0,
    }


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=20)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("scans", nargs="+")
    a = ap.parse_args()
    params = pypatchworkpp.Parameters()
    params.verbose = False
    params.sensor_height = 1.723  # Patchwork++'s own KITTI setting
    pw = pypatchworkpp.patchworkpp(params)
    times = []
    cpu_times = []
    counts = {"gmm": [0, 0, 0, 0], "terraseg": [0, 0, 0, 0]}  # tp, fp, fn, tn
    for path in a.scans:
        pts = np.fromfile(path, dtype=np.float32).reshape(-1, 4)
        for _ in range(a.warmup):
            pw.estimateGround(pts)
        for _ in range(a.repeat):
            t, c = time.perf_counter(), time.process_time()
            pw.estimateGround(pts)
            times.append((time.perf_counter() - t) * 1e3)
            cpu_times.append((time.process_time() - c) * 1e3)
        stem = os.path.splitext(os.path.basename(path))[0]
        label = os.path.join(os.path.dirname(os.path.dirname(path)), "labels", stem + ".label")
        if os.path.isfile(label):
            sem = np.fromfile(label, dtype=np.uint32) & 0xFFFF
            pred = np.zeros(len(pts), dtype=bool)
            pred[pw.getGroundIndices()] = True
            truth = np.isin(sem, list(GROUND))
            for protocol, ignored in (("gmm", IGNORED | VEGETATION), ("terraseg", IGNORED)):
                keep = ~np.isin(sem, list(ignored))
                c = counts[protocol]
                c[0] += int(np.sum(pred & truth & keep))
                c[1] += int(np.sum(pred & ~truth & keep))
                c[2] += int(np.sum(~pred & truth & keep))
                c[3] += int(np.sum(~pred & ~truth & keep))
    print(
        json.dumps(
            {
                "median_ms": statistics.median(times),
                "cpu_median_ms": statistics.median(cpu_times),
                "runs": len(times),
                "pooled": {p: metrics(*c) for p, c in counts.items()},
            }
        )
    )


if __name__ == "__main__":
    main()
