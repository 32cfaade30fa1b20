"""groundwork against Patchwork++ on labelled real scans of one sensor, as a user runs it:
`groundwork calibrate` over each sequence's raw scans, then `groundwork segment --config` with
the file it wrote; Patchwork++ (pypatchworkpp) on the same scans with the mount height that
calibrate found. Scored pooled over every labelled scan, gmm protocol (vegetation ignored):
ground IoU, precision, recall, ground recall per range, how many car points each calls
ground, and groundwork's reliability table (ten equal-width probability bins) with its
expected calibration error.

The data stays where it is (never copied into the repository): each SEQ is a folder with
velodyne/*.bin (f32 x, y, z, intensity) and labels/*.label (SemanticKITTI ids), e.g.
../shared/data/pandaset-001 or a local copy of the solid-state sequences 00-04 of
Neroxxc/mydataset-for-cylinder3D. Run through benches/real_sensors.sh.
    python real_sensors.py --groundwork BIN --sensor pandar64 SEQ [SEQ ...] [--json OUT]
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile
import tomllib

import numpy as np
import pypatchworkpp

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
LABELS = tomllib.load(open(os.path.join(ROOT, "config", "labels", "semantickitti.toml"), "rb"))
GROUND = np.array(LABELS["ground"])
IGNORED = np.array(LABELS["ignored"] + LABELS["vegetation"])  # gmm protocol
CAR = 10  # SemanticKITTI "car"
RANGES = [0, 5, 10, 20, 30, 40, 60, 100]
BINS = 10


class Score:
    """Pooled counts of one method over every labelled scan."""

    def __init__(self):
        self.tp = self.fp = self.fn = 0
        self.hit = np.zeros(len(RANGES) - 1)
        self.truth = np.zeros(len(RANGES) - 1)
        self.car = self.car_as_ground = 0
        self.bin_n = np.zeros(BINS)
        self.bin_p = np.zeros(BINS)
        self.bin_ground = np.zeros(BINS)

    def add(self, ground, truth, scored, rng, cls, prob=None):
        g, t = ground[scored], truth[scored]
        self.tp += int(np.sum(g & t))
        self.fp += int(np.sum(g & ~t))
        self.fn += int(np.sum(~g & t))
        ring = np.digitize(rng[scored], RANGES) - 1
        ok = (ring >= 0) & (ring < len(RANGES) - 1)
        np.add.at(self.truth, ring[ok & t], 1)
        np.add.at(self.hit, ring[ok & t & g], 1)
        car = cls == CAR
        self.car += int(np.sum(car))
        self.car_as_ground += int(np.sum(car & ground))
        if prob is not None:
            p = prob[scored].astype(np.float64)
            b = np.minimum((p * BINS).astype(int), BINS - 1)
            np.add.at(self.bin_n, b, 1)
            np.add.at(self.bin_p, b, p)
            np.add.at(self.bin_ground, b, t.astype(float))

    def summary(self):
        iou = 100 * self.tp / max(self.tp + self.fp + self.fn, 1)
        out = {
            "iou_ground": iou,
            "precision": 100 * self.tp / max(self.tp + self.fp, 1),
            "recall": 100 * self.tp / max(self.tp + self.fn, 1),
            "recall_by_range": {
                f"{a}-{b}": (100 * h / n if n else None)
                for a, b, h, n in zip(RANGES, RANGES[1:], self.hit, self.truth)
            },
            "ground_points_by_range": {f"{a}-{b}": int(n) for a, b, n in zip(RANGES, RANGES[1:], self.truth)},
            "car_points": self.car,
            "car_as_ground": self.car_as_ground,
        }
        if self.bin_n.sum():
            n = self.bin_n.sum()
            rows = []
            ece = 0.0
            for i in range(BINS):
                if self.bin_n[i]:
                    mp, fr = self.bin_p[i] / self.bin_n[i], self.bin_ground[i] / self.bin_n[i]
                    ece += self.bin_n[i] / n * abs(mp - fr)
                    rows.append({"bin": f"{i / BINS:.1f}-{(i + 1) / BINS:.1f}", "points": int(self.bin_n[i]),
                                 "mean_probability": mp, "ground_fraction": fr})
            out["reliability"] = rows
            out["ece"] = ece
        return out


def run(cmd):
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        sys.exit(f"{' '.join(cmd)} failed:\n{r.stderr}")
    return r.stdout


def usable(seq, spare):
    """The sequence as segment can read it: one with a poses.txt that does not list every
    scan (sequence 01 of the solid-state set lists 25 of 26) is read without its poses,
    through links in `spare`, and the log says so."""
    poses = os.path.join(seq, "poses.txt")
    scans = [n for n in os.listdir(os.path.join(seq, "velodyne")) if n.endswith(".bin")]
    if not os.path.exists(poses) or sum(1 for _ in open(poses)) == len(scans):
        return seq
    print(f"{seq}: poses.txt does not list every scan: segmented without poses", file=sys.stderr)
    os.makedirs(spare)
    for sub in ("velodyne", "labels"):
        os.symlink(os.path.abspath(os.path.join(seq, sub)), os.path.join(spare, sub))
    return spare


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--groundwork", required=True, help="the groundwork binary")
    ap.add_argument("--sensor", required=True, help="the preset calibrate starts from")
    ap.add_argument("--preset-only", action="store_true", help="segment with the preset, no calibrate")
    ap.add_argument("--overlay", help="a TOML laid over the preset, or appended to the calibrated file (e.g. `[terrain] enabled = true`)")
    ap.add_argument("--frames", type=int, help="history length for segment (default: the config's)")
    ap.add_argument("--json", help="also write the figures here")
    ap.add_argument("sequences", nargs="+")
    a = ap.parse_args()
    gw, pw = Score(), Score()
    tmp = tempfile.mkdtemp(prefix="real-sensors-")
    for k, seq in enumerate(a.sequences):
        seq = usable(seq, os.path.join(tmp, f"seq{k}"))
        scans = os.path.join(seq, "velodyne")
        cfg = ["--sensor", a.sensor] + (["--config", a.overlay] if a.overlay and a.preset_only else [])
        height = None
        if not a.preset_only:
            cal = os.path.join(tmp, f"cal{k}.toml")
            run([a.groundwork, "calibrate", "--sensor", a.sensor, "--out", cal, scans])
            if a.overlay:
                with open(cal, "a") as f:
                    f.write("\n" + open(a.overlay).read())
            cfg = ["--config", cal]
            height = tomllib.load(open(cal, "rb")).get("sensor", {}).get("mount", {}).get("height")
        if height is None:
            preset = os.path.join(ROOT, "config", "sensors", f"{a.sensor}.toml")
            height = tomllib.load(open(preset, "rb"))["sensor"]["mount"]["height"]
        out = os.path.join(tmp, f"seg{k}")
        frames = ["--frames", str(a.frames)] if a.frames else []
        run([a.groundwork, "segment", *cfg, *frames, "--out", out, seq])
        params = pypatchworkpp.Parameters()
        params.verbose = False
        params.sensor_height = float(height)
        patchwork = pypatchworkpp.patchworkpp(params)
        names = sorted(n[:-4] for n in os.listdir(scans) if n.endswith(".bin"))
        labelled = 0
        for name in names:
            pts = np.fromfile(os.path.join(scans, name + ".bin"), dtype=np.float32).reshape(-1, 4)
            patchwork.estimateGround(pts)  # every scan in order: Patchwork++ adapts scan to scan
            lab_path = os.path.join(seq, "labels", name + ".label")
            if not os.path.exists(lab_path):
                continue
            labelled += 1
            cls = np.fromfile(lab_path, dtype=np.uint32) & 0xFFFF
            truth = np.isin(cls, GROUND)
            scored = ~np.isin(cls, IGNORED)
            rng = np.hypot(pts[:, 0], pts[:, 1])
            prob = np.fromfile(os.path.join(out, name + ".prob"), dtype=np.float32)
            ground = np.fromfile(os.path.join(out, name + ".ground"), dtype=np.uint8).astype(bool)
            gw.add(ground, truth, scored, rng, cls, prob)
            pg = np.zeros(len(pts), dtype=bool)
            pg[patchwork.getGroundIndices()] = True
            pw.add(pg, truth, scored, rng, cls)
        print(f"{seq}: {labelled} labelled scans, mount height {height:.3f} m", file=sys.stderr)
    res = {"groundwork": gw.summary(), "patchwork++": pw.summary()}
    print(f"{'':14} {'IoU_g':>7} {'prec':>7} {'recall':>7} {'car->g %':>8}   recall by range (m): "
          + " ".join(f"{a}-{b}" for a, b in zip(RANGES, RANGES[1:])))
    for name, s in res.items():
        rr = " ".join("  -  " if v is None else f"{v:5.1f}" for v in s["recall_by_range"].values())
        car = 100 * s["car_as_ground"] / max(s["car_points"], 1)
        print(f"{name:14} {s['iou_ground']:7.2f} {s['precision']:7.2f} {s['recall']:7.2f} {car:8.2f}   {rr}")
    g = res["groundwork"]
    print(f"{'ground points':14} {'':34}" + " ".join(f"{n:5d}" if n < 1e5 else f"{n/1e3:4.0f}k" for n in g["ground_points_by_range"].values()))
    print(f"groundwork - Patchwork++: {g['iou_ground'] - res['patchwork++']['iou_ground']:+.2f} IoU points")
    print(f"reliability (groundwork): ECE {g['ece']:.3f}")
    print(f"  {'bin':8} {'points':>8} {'mean p':>7} {'ground':>7}")
    for r in g["reliability"]:
        print(f"  {r['bin']:8} {r['points']:8d} {r['mean_probability']:7.3f} {r['ground_fraction']:7.3f}")
    if a.json:
        json.dump(res, open(a.json, "w"), indent=1)


if __name__ == "__main__":
    main()
