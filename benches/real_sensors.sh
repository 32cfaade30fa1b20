#!/usr/bin/env bash
# groundwork (calibrate, then segment) against Patchwork++ on labelled real scans of one
# sensor, in one run: pooled ground IoU, per-range recall, car points called ground and the
# reliability table (benches/real_sensors.py says what each figure is). The scans stay where
# they are; nothing is copied into the repository.
#   bash benches/real_sensors.sh --sensor pandar64 ../shared/data/pandaset-001
#   bash benches/real_sensors.sh --sensor livox /path/to/mydataset-for-cylinder3D/{00,01,02,03,04}
# Options after --sensor: --preset-only (no calibrate), --overlay TOML (laid over the preset
# or appended to the calibrated file: quick experiments), --frames N, --json OUT.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/.." && pwd)
source "$here/patchwork_venv.sh"
cargo build --release --quiet --bin groundwork --manifest-path "$root/Cargo.toml"
exec "$venv/bin/python" "$here/real_sensors.py" --groundwork "$root/target/release/groundwork" "$@"
