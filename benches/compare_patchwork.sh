#!/usr/bin/env bash
# groundwork vs Patchwork++ (pypatchworkpp) on the same six KITTI scans, in one run.
# Installs pypatchworkpp into benches/.venv on first use. Prints each median and the ratio.
#   bash benches/compare_patchwork.sh [--repeat N]
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/.." && pwd)
repeat=${2:-20}
[ "${1:-}" = "--repeat" ] || repeat=20
source "$here/patchwork_venv.sh"
cargo build --release --quiet -p groundwork-benches --bin time-scans --manifest-path "$root/Cargo.toml"
scans=("$root"/tests/data/semantickitti-00/velodyne/*.bin)
# Alternate the two tools three times and take the median of medians, so that a noisy
# neighbour on this shared 2-core machine hits both alike.
gw=(); pw=()
for round in 1 2 3; do
  gw+=("$("$root/target/release/time-scans" --repeat "$repeat" "${scans[@]}" | python3 -c 'import json,sys; print(json.load(sys.stdin)["median_ms"])')")
  out=$("$venv/bin/python" "$here/patchwork_time.py" --repeat "$repeat" "${scans[@]}" | tail -n 1)
  pw+=("$(echo "$out" | python3 -c 'import json,sys; print(json.load(sys.stdin)["median_ms"])')")
done
python3 - "${gw[@]}" "${pw[@]}" <<'PY'
import statistics, sys
v = sys.argv[1:]
gw = statistics.median(map(float, v[0:3]))
pw = statistics.median(map(float, v[3:6]))
print(f"scans: 6 KITTI HDL-64E frames (~124k points), {len(v[0:3])} alternating rounds")
print(f"groundwork    median {gw:7.2f} ms/scan  (fit + query, single frame)")
print(f"Patchwork++   median {pw:7.2f} ms/scan  (pypatchworkpp 1.4.1; accuracy: benches/compare_methods.sh)")
print(f"ratio groundwork / Patchwork++ = {gw / pw:.2f}  (budget <= 1.33, goal <= 0.33)")
PY
