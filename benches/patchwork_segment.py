"""Patchwork++ (pypatchworkpp) as a whole process over a folder of KITTI .bin scans: the
yardstick for `groundwork segment DIR --out OUT` in benches/compare_offline.sh.

Reads every *.bin of the folder in name order, segments it, and writes <out>/<stem>.ground
(one u8 per point, 1 = ground), as groundwork's .ground files are. Serial, as Patchwork++'s
own examples run it: its estimateGround is single-threaded.
    python patchwork_segment.py SCANS_DIR OUT_DIR
"""
import os
import sys

import numpy as np
import pypatchworkpp


def main():
    scans, out = sys.argv[1], sys.argv[2]
    os.makedirs(out, exist_ok=True)
    params = pypatchworkpp.Parameters()
    params.verbose = False
    params.sensor_height = 1.723  # Patchwork++'s own KITTI setting
    pw = pypatchworkpp.patchworkpp(params)
    for name in sorted(os.listdir(scans)):
        if not name.endswith(".bin"):
            continue
        pts = np.fromfile(os.path.join(scans, name), dtype=np.float32).reshape(-1, 4)
        pw.estimateGround(pts)
        ground = np.zeros(len(pts), dtype=np.uint8)
        ground[pw.getGroundIndices()] = 1
        ground.tofile(os.path.join(out, name[:-4] + ".ground"))


if __name__ == "__main__":
    main()
