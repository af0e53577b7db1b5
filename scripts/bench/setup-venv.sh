#!/usr/bin/env bash
# Create (or reuse) the bench virtualenv at <repo>/.venv-bench: the peers the
# `bridgev2w bench` commands measure against (pybullet, scikit-image).
# Idempotent: if the venv already imports them, this is a no-op.
# Prints the path of the venv python on the last line of stdout.
set -euo pipefail

REPO_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
VENV="${REPO_ROOT}/.venv-bench"
PY="${VENV}/bin/python"
PYTHON="${PYTHON:-python3}"

if [[ -x "${PY}" ]] && "${PY}" -c "import pybullet, numpy, skimage" >/dev/null 2>&1; then
    echo "${PY}"
    exit 0
fi

if [[ ! -x "${PY}" ]]; then
    echo "creating venv at ${VENV}" >&2
    "${PYTHON}" -m venv "${VENV}"
fi

"${PY}" -m pip install --quiet --upgrade pip >&2
"${PY}" -m pip install --quiet "pybullet==3.2.7" numpy "scikit-image==0.26.0" >&2
"${PY}" -c "import pybullet, numpy, skimage" >&2
echo "${PY}"
