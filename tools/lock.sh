#!/usr/bin/env bash
# Regenerates requirements/lock.txt: the whole closure that tools/setup.sh installs (every path:
# `make demo`, `make test` with and without ../shared), pip and setuptools included, each with the
# sha256 of every file PyPI has for that release. Its inputs are the direct pins in requirements/*.txt
# and setup.py's install_requires; run it after changing them. uv resolves (from PyPI alone: no pip
# configuration, no local mirror) in a throwaway venv; installing uses plain pip (--require-hashes).
# The resolution is for this machine's kind: CPython 3.11 on x86_64 Linux.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
python3 -m venv "$tmp/venv"
"$tmp/venv/bin/python" -m pip install --isolated -q uv==0.13.9
inputs=(requirements/ros.txt requirements/build.txt requirements/dev.txt requirements/ros-tools.txt
  requirements/bench.txt setup.py)
env -u UV_INDEX_URL -u UV_EXTRA_INDEX_URL -u UV_FIND_LINKS "$tmp/venv/bin/uv" pip compile --no-config \
  --python python3 --generate-hashes --no-annotate --custom-compile-command tools/lock.sh \
  -o requirements/lock.txt "${inputs[@]}"
