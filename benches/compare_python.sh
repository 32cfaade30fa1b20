#!/usr/bin/env bash
# The Python package against Rust and Patchwork++, in one run: builds the `groundwork` wheel
# into benches/.venv (beside pypatchworkpp), then prints the per-scan time of
# Segmenter.segment from Python against the library's own time and the `time-scans` binary
# on the same scans (the overhead of a call), and runs examples/compare_patchwork.py.
#
#   bash benches/compare_python.sh [--repeat N]
set -euo pipefail
cd "$(dirname "$0")/.."
source benches/patchwork_venv.sh
export PATH="$venv/bin:$PATH"
python -m pip install -q --disable-pip-version-check -r crates/groundwork-py/requirements-test.txt
python -m pip install -q --disable-pip-version-check --no-build-isolation --force-reinstall --no-deps ./crates/groundwork-py
cargo build -q --release --locked -p groundwork-benches --bin time-scans
python crates/groundwork-py/bench.py --rust target/release/time-scans "$@" tests/data/semantickitti-00/velodyne/*.bin
python examples/compare_patchwork.py
