#!/usr/bin/env bash
# The Python package's tests: builds the `groundwork` wheel into a virtual environment
# (target/py-venv) and the CLI its results are compared with, then runs pytest. Arguments
# go to pytest.
set -euo pipefail
root=$(cd "$(dirname "$0")/../.." && pwd)
venv="$root/target/py-venv"
[ -x "$venv/bin/python" ] || python3 -m venv "$venv"
export PATH="$venv/bin:$PATH"
python -m pip install -q --disable-pip-version-check -r "$root/crates/groundwork-py/requirements-test.txt"
# The README's install line, with the build tools already in the environment.
python -m pip install -q --disable-pip-version-check --no-build-isolation --force-reinstall --no-deps \
    "$root/crates/groundwork-py"
cargo build -q --release --locked -p groundwork-cli
GROUNDWORK_CLI="$root/target/release/groundwork" python -m pytest -q "$root/crates/groundwork-py/tests" "$@"
# groundwork's packet decoding against independent decoders (velodyne-decoder, ouster-sdk,
# installed above): `cargo test` alone skips these, having no Python with the peers.
GROUNDWORK_PACKET_PEERS_PYTHON="$venv/bin/python" GROUNDWORK_REQUIRE_PACKET_PEERS=1 \
    cargo test -q --release --locked -p groundwork-packets --test velodyne_decoder --test ouster_sdk
