# A test venv over the project venv: `make_overlay_venv VENV LOCK CHECK`
# creates VENV with the pins of LOCK (installed with --no-deps) and a .pth
# file putting .venv's site-packages on its path, then runs the Python
# statement CHECK in it. Idempotent: a venv whose stamp matches LOCK is kept.
# Sourced by scripts/setup-lerobot-venv.sh, scripts/setup-policy-venv.sh and
# scripts/setup-mujoco-venv.sh.
make_overlay_venv() {
  local root venv="$1" lock="$2" check="$3" stamp project_site site
  root="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
  stamp="$venv/.bridgev2w-requirements"
  if [[ -x "$venv/bin/python" && -f "$stamp" ]] && cmp -s "$lock" "$stamp"; then
    return 0
  fi
  project_site="$("$root/.venv/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')"
  python3 -m venv "$venv"
  site="$("$venv/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')"
  echo "$project_site" > "$site/bridgev2w-project-venv.pth"
  local pins
  mapfile -t pins < <(grep -v -E '^[[:space:]]*(#|$)' "$lock")
  "$venv/bin/python" -m pip install --disable-pip-version-check --no-cache-dir --no-compile \
    --no-deps -q "${pins[@]}"
  "$venv/bin/python" -c "$check"
  cp "$lock" "$stamp"
}
