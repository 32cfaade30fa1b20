#!/usr/bin/env bash
# What keeping cores awake costs and buys in the service: the bundled pipeline run with
# `keep_awake_ms` at each given value, alternating, round after round. Prints, per setting, the
# medians over the rounds of the CPU time per scan of each stage and of the segment stage's
# and end-to-end latency percentiles (the consumer's report).
#   bash benches/compare_keep_awake.sh [--rounds R] [--count N] [MS ...]   (default: 10 0)
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
rounds=3
count=100
settings=()
while [ $# -gt 0 ]; do
  case "$1" in
    --rounds) rounds=$2; shift 2 ;;
    --count) count=$2; shift 2 ;;
    *) settings+=("$1"); shift ;;
  esac
done
[ ${#settings[@]} -gt 0 ] || settings=(10 0)
cargo build --release --quiet --locked -p groundwork-cli --manifest-path "$root/Cargo.toml"
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
for ((r = 1; r <= rounds; r++)); do
  for ms in "${settings[@]}"; do
    sed "s/^keep_awake_ms = .*/keep_awake_ms = $ms/" "$root/config/service.toml" >"$tmp/service-$ms.toml"
    "$root/target/release/groundwork" pipeline --count "$count" --prefix "keep-awake-$$" \
      --service "$tmp/service-$ms.toml" >"$tmp/out-$ms-$r.txt" 2>/dev/null
  done
done
python3 - "$tmp" "$rounds" "${settings[@]}" <<'PY'
import re, statistics, sys
tmp, rounds, settings = sys.argv[1], int(sys.argv[2]), sys.argv[3:]
med = statistics.median
print(f"{'keep_awake_ms':>13} {'CPU ms/scan: segmenter':>22} {'detector':>9} {'all stages':>10} {'segment p50':>12} {'e2e p50':>8} {'e2e p99':>8}")
for ms in settings:
    seg, det, tot, sp50, e50, e99 = [], [], [], [], [], []
    for r in range(1, rounds + 1):
        text = open(f"{tmp}/out-{ms}-{r}.txt").read()
        cpu = dict((k, float(v)) for k, v in re.findall(r"(\w+) ([\d.]+)", text.split("CPU per scan, ms: ")[1].split("\n")[0]))
        seg.append(cpu["segmenter"]); det.append(cpu.get("detector", 0.0)); tot.append(sum(cpu.values()))
        row = lambda name: [float(x) for x in re.search(rf"^{name}\s+\d+\s+([\d.]+)\s+([\d.]+)\s+([\d.]+)", text, re.M).groups()]
        sp50.append(row("segment")[0] / 1e3)
        e = row("end to end"); e50.append(e[0] / 1e3); e99.append(e[2] / 1e3)
    print(f"{ms:>13} {med(seg):>22.2f} {med(det):>9.2f} {med(tot):>10.2f} {med(sp50):>12.2f} {med(e50):>8.2f} {med(e99):>8.2f}")
print(f"(medians of {rounds} rounds; latencies in ms)")
PY
