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
gw=(); st=(); pw=()
median_of() { python3 -c 'import json,sys; print(json.load(sys.stdin)["median_ms"])'; }
for round in 1 2 3; do
  gw+=("$("$root/target/release/time-scans" --repeat "$repeat" "${scans[@]}" | median_of)")
  # Streaming: the sequence replayed in order with its poses, default history.
  st+=("$("$root/target/release/time-scans" --repeat "$((repeat / 2))" --sequence "$root/tests/data/semantickitti-00" | median_of)")
  out=$("$venv/bin/python" "$here/patchwork_time.py" --repeat "$repeat" "${scans[@]}" | tail -n 1)
  pw+=("$(echo "$out" | python3 -c 'import json,sys; print(json.load(sys.stdin)["median_ms"])')")
done
python3 - "${gw[@]}" "${st[@]}" "${pw[@]}" <<'PY'
import statistics, sys
v = sys.argv[1:]
gw = statistics.median(map(float, v[0:3]))
st = statistics.median(map(float, v[3:6]))
pw = statistics.median(map(float, v[6:9]))
print(f"scans: 6 KITTI HDL-64E frames (~124k points), {len(v[0:3])} alternating rounds")
print(f"groundwork    median {gw:7.2f} ms/scan  (fit + query, single frame)")
print(f"Patchwork++   median {pw:7.2f} ms/scan  (pypatchworkpp 1.4.1; accuracy: benches/compare_methods.sh)")
print(f"groundwork    median {st:7.2f} ms/scan  (streaming: the sequence in order with poses, default history)")
print(f"ratio groundwork / Patchwork++ = {gw / pw:.2f} cold single scan (goal <= 0.45), {st / pw:.2f} streaming (goal <= 0.3)")
PY
