"""Times Patchwork++ (pypatchworkpp) on KITTI scans and scores it on the labeled ones.

Each scan is loaded once, segmented --repeat times after --warmup untimed runs; prints JSON
with the median time per scan and the pooled ground metrics (gmm protocol) on scans that
have a labels/<stem>.label beside velodyne/.
"""
import argparse
import json
import os
import statistics
import time

import numpy as np
import pypatchworkpp

GROUND = {40, 44, 48, 49, 60, 72}
IGNORED_GMM = {0, 1, 70}


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
    times, tp, fp, fn = [], 0, 0, 0
    for path in a.scans:
        pts = np.fromfile(path, dtype=np.float32).reshape(-1, 4)
        for _ in range(a.warmup):
            pw.estimateGround(pts)
        for _ in range(a.repeat):
            t = time.perf_counter()
            pw.estimateGround(pts)
            times.append((time.perf_counter() - t) * 1e3)
        stem = os.path.splitext(os.path.basename(path))[0]
        label = os.path.join(os.path.dirname(os.path.dirname(path)), "labels", stem + ".label")
        if os.path.isfile(label):
            sem = np.fromfile(label, dtype=np.uint32) & 0xFFFF
            pred = np.zeros(len(pts), dtype=bool)
            pred[pw.getGroundIndices()] = True
            keep = ~np.isin(sem, list(IGNORED_GMM))
            truth = np.isin(sem, list(GROUND))
            tp += int(np.sum(pred & truth & keep))
            fp += int(np.sum(pred & ~truth & keep))
            fn += int(np.sum(~pred & truth & keep))
    iou = 100.0 * tp / max(tp + fp + fn, 1)
    print(json.dumps({"median_ms": statistics.median(times), "runs": len(times), "pooled_ground_iou": iou}))


if __name__ == "__main__":
    main()
