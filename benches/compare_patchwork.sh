#!/usr/bin/env bash
# groundwork vs Patchwork++ (pypatchworkpp) on the same six KITTI scans, in one run.
# Installs pypatchworkpp into benches/.venv on first use. Prints each median and the ratios.
#   bash benches/compare_patchwork.sh [--repeat N] [--rounds R]
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/.." && pwd)
repeat=20
rounds=3
while [ $# -gt 0 ]; do
  case "$1" in
    --repeat) repeat=$2; shift 2 ;;
    --rounds) rounds=$2; shift 2 ;;
    *) echo "usage: $0 [--repeat N] [--rounds R]" >&2; exit 2 ;;
  esac
done
source "$here/patchwork_venv.sh"
cargo build --release --quiet -p groundwork-benches --bin time-scans --manifest-path "$root/Cargo.toml"
scans=("$root"/tests/data/semantickitti-00/velodyne/*.bin)
# The tools take turns, round after round, and each round gives its own ratios: a noisy
# neighbour on this shared 2-core machine slows a whole round, both tools alike, so the
# ratios of a round travel better than medians taken apart.
gw=(); st=(); pw=()
median_of() { python3 -c 'import json,sys; print(json.load(sys.stdin)["median_ms"])'; }
for ((round = 1; round <= rounds; round++)); do
  gw+=("$("$root/target/release/time-scans" --repeat "$repeat" "${scans[@]}" | median_of)")
  # Streaming: the sequence replayed in order with its poses, default history.
  st+=("$("$root/target/release/time-scans" --repeat "$((repeat / 2))" --sequence "$root/tests/data/semantickitti-00" | median_of)")
  out=$("$venv/bin/python" "$here/patchwork_time.py" --repeat "$repeat" "${scans[@]}" | tail -n 1)
  pw+=("$(echo "$out" | python3 -c 'import json,sys; print(json.load(sys.stdin)["median_ms"])')")
done
python3 - "$rounds" "${gw[@]}" "${st[@]}" "${pw[@]}" <<'PY'
import statistics, sys
r = int(sys.argv[1])
v = list(map(float, sys.argv[2:]))
gw, st, pw = v[0:r], v[r:2 * r], v[2 * r:3 * r]
med = statistics.median
cold = [g / p for g, p in zip(gw, pw)]
stream = [s / p for s, p in zip(st, pw)]
print(f"scans: 6 KITTI HDL-64E frames (~124k points), {r} alternating rounds")
print(f"groundwork    median {med(gw):7.2f} ms/scan  (fit + query, single frame)")
print(f"Patchwork++   median {med(pw):7.2f} ms/scan  (pypatchworkpp 1.4.1; accuracy: benches/compare_methods.sh)")
print(f"groundwork    median {med(st):7.2f} ms/scan  (streaming: the sequence in order with poses, default history)")
print(f"ratio groundwork / Patchwork++, median of the rounds' ratios: {med(cold):.2f} cold single scan "
      f"({min(cold):.2f}-{max(cold):.2f}), {med(stream):.2f} streaming "
      f"({min(stream):.2f}-{max(stream):.2f})")
PY
