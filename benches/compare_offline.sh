#!/usr/bin/env bash
# Offline throughput: `groundwork segment` over a folder of 60 KITTI scans against Patchwork++
# (pypatchworkpp) over the same folder, each a whole process (start-up, reading, writing the
# per-point outputs included), alternating A B A B so that a noisy neighbour hits both alike.
# Prints each median and the median of the per-pair ratios.
#   bash benches/compare_offline.sh [--rounds N] [-- extra groundwork segment args]
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/.." && pwd)
rounds=7
if [ "${1:-}" = "--rounds" ]; then rounds=$2; shift 2; fi
[ "${1:-}" = "--" ] && shift
source "$here/patchwork_venv.sh"
cargo build --release --quiet -p groundwork-cli --manifest-path "$root/Cargo.toml"
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
# 60 scans: the six bundled frames ten times over, without poses (so single-frame: each scan
# on its own, as Patchwork++ sees them).
mkdir "$work/scans"
src=("$root"/tests/data/semantickitti-00/velodyne/*.bin)
for i in $(seq 0 59); do
  cp "${src[$((i % ${#src[@]}))]}" "$(printf '%s/scans/%06d.bin' "$work" "$i")"
done
"$venv/bin/python" - "$rounds" "$work" "$root/target/release/groundwork" "$venv/bin/python" \
  "$here/patchwork_segment.py" "$@" <<'PY'
import os, shutil, statistics, subprocess, sys, time
rounds, work, gw, py, pw_script, extra = int(sys.argv[1]), sys.argv[2], sys.argv[3], sys.argv[4], sys.argv[5], sys.argv[6:]
scans = os.path.join(work, "scans")
cmds = {
    "groundwork": [gw, "segment", scans, "--out", os.path.join(work, "gw"), *extra],
    "Patchwork++": [py, pw_script, scans, os.path.join(work, "pw")],
}
def run(cmd):
    t = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                   env={**os.environ, "RUST_LOG": "warn"})
    return time.perf_counter() - t
for c in cmds.values():  # warm-up: page cache, output folders
    run(c)
times = {k: [] for k in cmds}
for _ in range(rounds):
    for k, c in cmds.items():
        times[k].append(run(c))
gw_t, pw_t = times["groundwork"], times["Patchwork++"]
ratios = sorted(a / b for a, b in zip(gw_t, pw_t))
n = len(os.listdir(scans))
print(f"{n} KITTI HDL-64E scans (~124k points) in one folder, {rounds} alternating rounds, whole processes")
print(f"groundwork segment   median {statistics.median(gw_t):6.2f} s  ({1e3 * statistics.median(gw_t) / n:5.1f} ms/scan)  {' '.join(extra)}")
print(f"Patchwork++ (Python) median {statistics.median(pw_t):6.2f} s  ({1e3 * statistics.median(pw_t) / n:5.1f} ms/scan)  pypatchworkpp 1.4.1")
print(f"ratio groundwork / Patchwork++, pair by pair: median {statistics.median(ratios):.2f} (min {ratios[0]:.2f}, max {ratios[-1]:.2f})")
PY
