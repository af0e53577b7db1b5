#!/usr/bin/env bash
# Create (or reuse) the pybullet bench virtualenv at <repo>/.venv-bench.
# Idempotent: if the venv already imports pybullet and numpy, this is a no-op.
# Prints the path of the venv python on the last line of stdout.
set -euo pipefail

REPO_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
VENV="${REPO_ROOT}/.venv-bench"
PY="${VENV}/bin/python"
PYTHON="${PYTHON:-python3}"

if [[ -x "${PY}" ]] && "${PY}" -c "import pybullet, numpy" >/dev/null 2>&1; then
    echo "${PY}"
    exit 0
fi

if [[ ! -x "${PY}" ]]; then
    echo "creating venv at ${VENV}" >&2
    "${PYTHON}" -m venv "${VENV}"
fi

"${PY}" -m pip install --quiet --upgrade pip >&2
"${PY}" -m pip install --quiet "pybullet==3.2.7" numpy >&2
"${PY}" -c "import pybullet, numpy" >&2
echo "${PY}"
