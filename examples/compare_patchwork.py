"""groundwork and Patchwork++ side by side on one KITTI scan: ground fraction, ground IoU
against the SemanticKITTI labels (gmm protocol: vegetation ignored) and time per call.

    bash benches/compare_python.sh          # builds both into benches/.venv, runs this
    python examples/compare_patchwork.py [scan.bin] [scan.label]
"""
import sys
import time

import numpy as np

import groundwork

scan = sys.argv[1] if len(sys.argv) > 1 else "tests/data/semantickitti-00/velodyne/000000.bin"
label = sys.argv[2] if len(sys.argv) > 2 else "tests/data/semantickitti-00/labels/000000.label"
points = np.fromfile(scan, dtype=np.float32).reshape(-1, 4)  # x, y, z, intensity
labels = np.fromfile(label, dtype=np.uint32)

# groundwork: a probability per point, in input order.
segmenter = groundwork.Segmenter(sensor="hdl64e")
t = time.perf_counter()
probs = segmenter.segment(points)
ms = (time.perf_counter() - t) * 1e3
ground = probs >= segmenter.threshold
m = groundwork.evaluate(probs, labels)
print(f"groundwork    ground {ground.mean():6.1%}  IoU {m['iou_ground']:5.2f}  {ms:6.1f} ms")

# Patchwork++: indices of the ground points.
import pypatchworkpp

params = pypatchworkpp.Parameters()
patchwork = pypatchworkpp.patchworkpp(params)
t = time.perf_counter()
patchwork.estimateGround(points)
ms = (time.perf_counter() - t) * 1e3
mask = np.zeros(len(points), dtype=np.float32)
mask[patchwork.getGroundIndices()] = 1.0
m = groundwork.evaluate(mask, labels)
print(f"Patchwork++   ground {mask.mean():6.1%}  IoU {m['iou_ground']:5.2f}  {ms:6.1f} ms")
