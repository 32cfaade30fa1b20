#!/usr/bin/env bash
# The segment stage of the running service against Patchwork++ in the same run:
# `groundwork pipeline --count N` (producer, segmenter, detector and consumer as processes on
# the bundled sequence, poses and default history) with and without the detector stage, and
# Patchwork++'s in-process per-scan median (benches/patchwork_time.py) on the same scans,
# alternating, --rounds times. Prints the medians of the segment stage's p50 (the consumer's
# table) and the ratios, the CPU time per scan of the segmenter and detector processes (the
# consumer's report) against Patchwork++'s CPU time per scan, and, to show where the stage's
# time goes beyond the bench's, the same streaming in one process (time-scans --sequence)
# back to back and paced at the sensor's 10 Hz (--period-ms 100: the cores idle between
# scans as they do in the service), and the pipeline once more with the stages' workers
# kept awake (keep_awake_ms = 10, see config/service.toml).
#   bash benches/compare_pipeline.sh [--rounds N] [--count N]
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/.." && pwd)
rounds=3; count=120
while [ $# -gt 0 ]; do
  case $1 in
    --rounds) rounds=$2; shift 2 ;;
    --count) count=$2; shift 2 ;;
    *) echo "unknown argument $1" >&2; exit 2 ;;
  esac
done
source "$here/patchwork_venv.sh"
cargo build --release --quiet -p groundwork-cli -p groundwork-benches --manifest-path "$root/Cargo.toml"
gw="$root/target/release/groundwork"
ts="$root/target/release/time-scans"
seq_dir="$root/tests/data/semantickitti-00"
scans=("$root"/tests/data/semantickitti-00/velodyne/*.bin)
# p50 of the consumer's "segment" row, in ms.
segment_p50() { awk '$1 == "segment" && $2 ~ /^[0-9]+$/ { printf "%.3f\n", $3 / 1000 }' | tail -n 1; }
# Field $1 of a JSON object on stdin; median_of: the time-scans / patchwork_time.py median.
json_field() { python3 -c 'import json,sys; print(json.load(sys.stdin)[sys.argv[1]])' "$1"; }
median_of() { json_field median_ms; }
# The consumer's "CPU per scan, ms: ... segmenter X" line: process $1's figure.
cpu_of() { awk -v p="$1" '/^CPU per scan, ms:/ { for (i = 1; i < NF; i++) if ($i == p) { v = $(i + 1); sub(",", "", v); print v } }' | tail -n 1; }
awake_cfg=$(mktemp --suffix=.toml)
trap 'rm -f "$awake_cfg"' EXIT
sed 's/^keep_awake_ms = .*/keep_awake_ms = 10.0/' "$root/config/service.toml" > "$awake_cfg"
with=(); without=(); pw=(); bench=(); paced=(); awake=(); seg_cpu=(); det_cpu=(); pw_cpu=()
for round in $(seq "$rounds"); do
  report=$(RUST_LOG=warn "$gw" pipeline --count "$count" --prefix "gw-bench-$$-a$round" 2>&1)
  with+=("$(segment_p50 <<< "$report")")
  seg_cpu+=("$(cpu_of segmenter <<< "$report")")
  det_cpu+=("$(cpu_of detector <<< "$report")")
  without+=("$(RUST_LOG=warn "$gw" pipeline --count "$count" --no-detector --prefix "gw-bench-$$-b$round" 2>&1 | segment_p50)")
  awake+=("$(RUST_LOG=warn "$gw" pipeline --count "$count" --service "$awake_cfg" --prefix "gw-bench-$$-c$round" 2>&1 | segment_p50)")
  pw_json=$("$venv/bin/python" "$here/patchwork_time.py" --repeat 10 "${scans[@]}" | tail -n 1)
  pw+=("$(median_of <<< "$pw_json")")
  pw_cpu+=("$(json_field cpu_median_ms <<< "$pw_json")")
  bench+=("$("$ts" --repeat 6 --sequence "$seq_dir" | median_of)")
  paced+=("$("$ts" --repeat 6 --sequence "$seq_dir" --period-ms 100 | median_of)")
done
python3 - "$rounds" "$count" "${with[@]}" "${without[@]}" "${pw[@]}" "${bench[@]}" "${paced[@]}" "${awake[@]}" "${seg_cpu[@]}" "${det_cpu[@]}" "${pw_cpu[@]}" <<'PY'
import statistics, sys
r, count, v = int(sys.argv[1]), sys.argv[2], [float(x) for x in sys.argv[3:]]
with_, without, pw, bench, paced, awake, seg_cpu, det_cpu, pw_cpu = (
    statistics.median(v[i * r:(i + 1) * r]) for i in range(9)
)
print(f"groundwork pipeline --count {count}: segment stage p50, median of {r} runs (poses, default history)")
print(f"  with the detector stage beside it   {with_:7.2f} ms   ratio {with_ / pw:.2f}")
print(f"  --no-detector                       {without:7.2f} ms   ratio {without / pw:.2f}")
print(f"  with the detector, keep_awake_ms = 10 {awake:5.2f} ms   ratio {awake / pw:.2f}")
print(f"Patchwork++ in-process, same scans    {pw:7.2f} ms/scan (pypatchworkpp 1.4.1)   goal: ratio <= 0.5")
print("CPU time per scan (the consumer's report for the run with the detector; Patchwork++'s process CPU per call):")
print(f"  segmenter process                   {seg_cpu:7.2f} ms   ratio {seg_cpu / pw_cpu:.2f}")
print(f"  detector process                    {det_cpu:7.2f} ms   ratio {det_cpu / pw_cpu:.2f}")
print(f"  Patchwork++, one thread             {pw_cpu:7.2f} ms   goal: segmenter ratio <= 1")
print("the same streaming in one process (time-scans --sequence):")
print(f"  back to back (the bench)            {bench:7.2f} ms   ratio {bench / pw:.2f}")
print(f"  paced at 10 Hz (--period-ms 100)    {paced:7.2f} ms   ratio {paced / pw:.2f}")
PY
