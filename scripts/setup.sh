#!/bin/sh
# One-step set-up on Debian/Ubuntu: system packages, then a virtual environment in .venv
# with hemirad installed (editable). `scripts/setup.sh --test` adds the test extras.
set -eu
cd "$(dirname "$0")/.."

scripts/install_system_deps.sh
[ -x .venv/bin/python ] || python3 -m venv .venv
extras=""
[ "${1:-}" = "--test" ] && extras="[test]"
.venv/bin/python -m pip install --quiet --disable-pip-version-check -e ".$extras"
