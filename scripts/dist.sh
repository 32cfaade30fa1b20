#!/usr/bin/env bash
# Release artifacts, all from this one script, into dist/:
#   groundwork-<version>-<target>.tar.gz   for x86_64- and aarch64-unknown-linux-gnu:
#       bin/groundwork, share/groundwork/{config,semantickitti-00}, README.md, licences;
#       the binary linked by zig against glibc 2.17's symbols (cargo-zigbuild), so it runs on
#       any Linux since 2014 (Ubuntu 18.04/20.04, JetPack 5, Debian 10...), not only on one
#       as new as the build machine
#   groundwork-<version>-cp39-abi3-manylinux_2_17_<arch>.whl   the Python package, one wheel per
#       CPU for every CPython ≥ 3.9, built by maturin with zig as the linker (glibc 2.17)
# Each wheel is checked with `auditwheel show`, each binary's newest glibc symbol printed.
# Options: --targets "x86_64 aarch64" (default both), --no-wheels, --no-tarballs. The build
# tools (maturin, cargo-zigbuild, ziglang, auditwheel, pinned in scripts/requirements-dist.txt)
# go into target/dist-venv; zig cross-links, so aarch64 needs only
# `rustup target add aarch64-unknown-linux-gnu` (added here).
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
cd "$root"
targets="x86_64 aarch64"
wheels=1
tarballs=1
while [ $# -gt 0 ]; do
    case "$1" in
    --targets) targets=$2; shift 2 ;;
    --no-wheels) wheels=""; shift ;;
    --no-tarballs) tarballs=""; shift ;;
    *) echo "dist.sh: unknown option $1" >&2; exit 2 ;;
    esac
done
version=$(sed -n 's/^version = "\(.*\)"$/\1/p' Cargo.toml | head -1)
host=$(rustc -vV | sed -n 's/^host: //p')
mkdir -p dist
venv=$root/target/dist-venv
[ -x "$venv/bin/python" ] || python3 -m venv "$venv"
"$venv/bin/python" -m pip install -q --disable-pip-version-check -r scripts/requirements-dist.txt
# cargo-zigbuild and maturin find zig as `python3 -m ziglang` of this environment.
export PATH="$venv/bin:$PATH"

for arch in $targets; do
    triple=$arch-unknown-linux-gnu
    [ "$triple" = "$host" ] || rustup target add "$triple" >/dev/null
    if [ -n "$tarballs" ]; then
        echo "== $triple: groundwork binary (glibc 2.17)"
        cargo-zigbuild zigbuild --release --locked --target "$triple.2.17" -p groundwork-cli
        bin=target/$triple/release/groundwork
        echo "newest glibc symbol: $(objdump -T "$bin" | grep -o 'GLIBC_[0-9.]*' | sort -uV | tail -1)"
        name=groundwork-$version-$triple
        stage=target/dist/$name
        rm -rf "$stage"
        mkdir -p "$stage/bin" "$stage/share/groundwork"
        cp "$bin" "$stage/bin/"
        cp -r config "$stage/share/groundwork/"
        cp -r tests/data/semantickitti-00 "$stage/share/groundwork/"
        cp README.md LICENSE-MIT LICENSE-APACHE "$stage/"
        tar -C target/dist -czf "dist/$name.tar.gz" "$name"
        echo "dist/$name.tar.gz"
    fi
done

if [ -n "$wheels" ]; then
    for arch in $targets; do
        triple=$arch-unknown-linux-gnu
        echo "== $triple: Python wheel"
        # zig links against glibc 2.17's symbols: the wheel is manylinux2014, for any distro
        # since 2014 (CentOS 7, Ubuntu 14.04, Debian 8), whatever this machine's glibc is.
        maturin build --release --locked --zig \
            --compatibility manylinux2014 --target "$triple" \
            -m crates/groundwork-py/Cargo.toml --out dist
        wheel=$(ls -t dist/groundwork-"$version"-*abi3*"$arch".whl | head -1)
        "$venv/bin/auditwheel" show "$wheel"
    done
fi
ls -l dist
