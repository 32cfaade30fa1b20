#!/usr/bin/env bash
# Accuracy of every method on the labeled bundled frames (0-2), both protocols, with
# Patchwork++ (pypatchworkpp) scored in the same run on the same scans and classes: each
# scan segmented once, in order (Patchwork++ adapts its thresholds from scan to scan).
#   bash benches/compare_methods.sh
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/.." && pwd)
source "$here/patchwork_venv.sh"
cargo build --release --quiet --bin groundwork --manifest-path "$root/Cargo.toml"
seq="$root/tests/data/semantickitti-00"
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
for protocol in gmm terraseg; do
  "$root/target/release/groundwork" eval --frames 1 --method gmm,pseudolabeler,ransac \
    --protocol "$protocol" --json "$seq" >"$tmp/$protocol.json" 2>/dev/null
  "$root/target/release/groundwork" eval --method gmm --protocol "$protocol" --json "$seq" \
    >"$tmp/$protocol-history.json" 2>/dev/null
done
"$venv/bin/python" "$here/patchwork_time.py" --repeat 1 --warmup 0 "$seq"/velodyne/*.bin 2>/dev/null |
  tail -n 1 >"$tmp/patchwork.json"
python3 - "$tmp" <<'PY'
import json, sys
d = sys.argv[1]
def load(n):
    r = json.load(open(f"{d}/{n}.json"))
    return r if isinstance(r, list) else [r]  # one method: one report, several: an array
rows = {}
for protocol in ("gmm", "terraseg"):
    for r in load(protocol) + load(f"{protocol}-history"):
        name = r["method"] if r["history_frames"] == 1 else f"{r['method']}, {r['history_frames']} frames"
        rows.setdefault(name, {})[protocol] = (r["pooled_metrics"], r["median_ms"])
pw = load("patchwork")[0]
rows["Patchwork++ 1.4.1"] = {p: (m, pw["median_ms"]) for p, m in pw["pooled"].items()}
print("frames 0-2 pooled; terraseg: vegetation is non-ground, gmm: vegetation ignored")
print(f"{'method':22} {'ts mIoU':>8} {'ts IoU_g':>8} {'gmm IoU_g':>9} {'gmm prec':>8} {'gmm mIoU':>8} {'ms/scan':>8}")
for name, r in rows.items():
    t, g = r["terraseg"][0], r["gmm"][0]
    print(f"{name:22} {t['miou']:8.2f} {t['iou_ground']:8.2f} {g['iou_ground']:9.2f} "
          f"{g['precision']:8.2f} {g['miou']:8.2f} {r['gmm'][1]:8.1f}")
PY
