# Sourced by the benches scripts: a virtual environment with Patchwork++'s Python package
# (pypatchworkpp, pinned) in benches/.venv, created on first use. Sets $venv.
venv="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)/.venv"
if [ ! -x "$venv/bin/python" ]; then
  python3 -m venv "$venv"
  "$venv/bin/pip" install --quiet pypatchworkpp==1.4.1 numpy
fi
