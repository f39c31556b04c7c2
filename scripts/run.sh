#!/usr/bin/env bash
# One entry point for a fresh machine: creates .venv (Python >= 3.12, found by itself), installs the
# project, then runs a job (scripts/run.sh --help: this text).
#   scripts/run.sh demo   - the main job on the built-in default (no dataset, GPU or network)
#   scripts/run.sh test   - lint + the fast test tier (slow tests skipped), on 2 pytest-xdist workers
#   scripts/run.sh test -m slow - lint + only the slow tier (benchmark-like tests); other args go to pytest
#                           (-n 0: one process; LEROBOT_FORMATION_TEST_WORKERS=N: N workers)
#   scripts/run.sh setup  - only create/refresh the environment (one [setup] line per stage, with its
#                           time and the size of .venv: docs/setup.md)
# Threads: OMP_NUM_THREADS and MKL_NUM_THREADS default to 1 (the models are tiny; more threads on a
# small or shared machine oversubscribe the cores); set them, or LEROBOT_FORMATION_THREADS, or pass
# --threads N to the demo, to use more.
# Torch: on a machine without an NVIDIA GPU (no working nvidia-smi) setup first installs the CPU build
# of torch and torchvision from the PyTorch CPU index (far smaller than PyPI's ~5.7 GB CUDA build with
# its nvidia-* wheels); if that index cannot be reached it says so in one line and PyPI's CUDA build is
# installed as usual. LEROBOT_FORMATION_TORCH=cuda always takes PyPI's build, =cpu takes the CPU index
# even with a GPU (default: auto). LEROBOT_FORMATION_TORCH_INDEX overrides the index URL. The choice is
# made when .venv is set up: to switch, remove .venv first.
set -euo pipefail
cd "$(dirname "$0")/.."
export HF_HUB_OFFLINE=1 HF_DATASETS_OFFLINE=1 TOKENIZERS_PARALLELISM=false
export OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}" MKL_NUM_THREADS="${MKL_NUM_THREADS:-${OMP_NUM_THREADS:-1}}"

find_python() {
  local c v
  # 3.12 first: the version lerobot 0.6.1 and its wheels are known to work with here.
  for c in python3.12 python3.13 python3 python; do
    if command -v "$c" >/dev/null 2>&1 && "$c" -c 'import sys; sys.exit(sys.version_info < (3, 12))' 2>/dev/null; then
      command -v "$c"; return 0
    fi
  done
  # pyenv keeps other versions out of PATH unless selected: look in its versions folder.
  local root="${PYENV_ROOT:-$HOME/.pyenv}"
  if command -v pyenv >/dev/null 2>&1; then root="$(pyenv root)"; fi
  for v in $(ls -d "$root"/versions/3.12* 2>/dev/null | sort -V -r) $(ls -d "$root"/versions/3.1[3-9]* 2>/dev/null | sort -V); do
    if [ -x "$v/bin/python3" ] && "$v/bin/python3" -c 'import sys; sys.exit(sys.version_info < (3, 12))'; then
      echo "$v/bin/python3"; return 0
    fi
  done
  for c in /usr/bin/python3.12 /usr/local/bin/python3.12 /usr/bin/python3.1[3-9] /usr/local/bin/python3.1[3-9]; do
    [ -x "$c" ] && { echo "$c"; return 0; }
  done
  return 1
}

# pyproject's torch range; torchvision's is lerobot 0.6.1's (each torchvision pins one torch release,
# so pip picks a matching pair from the one index).
TORCH_SPECS=('torch>=2.7,<2.12' 'torchvision>=0.22,<0.27')
TORCH_CPU_INDEX="${LEROBOT_FORMATION_TORCH_INDEX:-https://download.pytorch.org/whl/cpu}"

install_cpu_torch() {
  local choice="${LEROBOT_FORMATION_TORCH:-auto}"
  case "$choice" in
    cuda) return 0 ;;
    auto) if command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L >/dev/null 2>&1; then return 0; fi ;;
    cpu) ;;
    *) echo "error: LEROBOT_FORMATION_TORCH must be auto, cpu or cuda, got '$choice'" >&2; exit 2 ;;
  esac
  # Probe the index first (5 s, no retries), so an unreachable one costs seconds, not pip's retry loop.
  if ! .venv/bin/python - "$TORCH_CPU_INDEX/torch/" <<'PY' 2>/dev/null; then
import sys, urllib.request
urllib.request.urlopen(sys.argv[1], timeout=5).close()
PY
    echo "note: the PyTorch CPU index $TORCH_CPU_INDEX is unreachable; installing the CUDA build of torch from PyPI"
    return 0
  fi
  echo "no NVIDIA GPU (or LEROBOT_FORMATION_TORCH=cpu): installing the CPU build of torch from $TORCH_CPU_INDEX"
  local log
  if log="$(.venv/bin/python -m pip install -q --timeout 15 --retries 0 --index-url "$TORCH_CPU_INDEX" "${TORCH_SPECS[@]}" 2>&1)"; then
    printf '%s\n' "$log" | grep -v -e "^WARNING: Location" -e '^$' || true
  else
    echo "note: the CPU build could not be installed (${log##*$'\n'}); installing the CUDA build of torch from PyPI"
  fi
}

# Setup talks: one line per stage with its time and the size of .venv after it (docs/setup.md).
venv_size() {
  du -sk .venv 2>/dev/null | awk '{ if ($1 >= 1048576) printf "%.1f GB", $1 / 1048576; else printf "%d MB", $1 / 1024 }'
}
stage_done() { echo "[setup] $1 in $((SECONDS - $2)) s, .venv now $(venv_size)"; }

# pip's output without its noise: the "Location" warnings, blank lines and setuptools' warning boxes
# (the editable install's "InformationOnly: Editable installation" box: a `file.py:N: Category: text`
# header, a block between two "!!" lines, then the indented source line). Anything else is kept.
quiet_pip() {
  awk '
    box == 0 && held == "" && /\.py:[0-9]+: [A-Za-z]*(Warning|InformationOnly): / { held = $0; next }
    held != "" && $0 == "!!" { box = 1; held = ""; next }
    held != "" { print held; held = "" }
    box == 1 { if ($0 == "!!") box = 2; next }
    box == 2 { box = 0; if ($0 ~ /^  /) next }
    /^WARNING: Location/ || /^[[:space:]]*$/ { next }
    /^Editable install will be performed using a meta path finder\.$/ { next }
    /^Options like `package-data`/ || /^`packages\.find\.exclude\/include` may have no effect\.$/ { next }
    { print }
    END { if (held != "") print held }
  '
}

torch_build() {
  .venv/bin/python -c 'import torch; print(torch.__version__.split("+")[0], "(CUDA build)" if torch.version.cuda else "(CPU build)")'
}

setup() {
  local stamp=.venv/.installed
  local want start
  want="$(sha256sum < pyproject.toml | cut -c1-16)"
  if [ -x .venv/bin/python ] && [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ]; then
    return 0
  fi
  start=$SECONDS
  if [ ! -x .venv/bin/python ]; then
    local py
    py="$(find_python)" || { echo "error: no Python >= 3.12 found (PATH, pyenv, /usr/bin)" >&2; exit 1; }
    echo "[setup] creating .venv with $py ($("$py" --version 2>&1)); a first setup takes minutes and GBs (docs/setup.md)"
    "$py" -m venv .venv
  fi
  .venv/bin/python -m pip install -q --upgrade pip 2>&1 | quiet_pip || true
  stage_done "environment and pip ready" "$start"
  # An installed torch satisfies the project's pins, so the next install keeps it.
  if ! .venv/bin/python -c 'import torch' 2>/dev/null; then
    start=$SECONDS
    install_cpu_torch
    if ! .venv/bin/python -c 'import torch' 2>/dev/null; then
      echo "[setup] installing torch from PyPI (the CUDA build and its nvidia-* wheels: the largest download)"
      .venv/bin/python -m pip install -q "${TORCH_SPECS[@]}" 2>&1 | quiet_pip || true
    fi
    stage_done "torch $(torch_build 2>/dev/null || echo '(not importable)') installed" "$start"
  fi
  start=$SECONDS
  # One distribution, lerobot_env_formation (the name LeRobot's CLIs discover), holds the plugin and its
  # discovery module. A .venv of the earlier layout also has the distribution lerobot_formation (the
  # shim was a second one): uninstall it first, as its files include the console scripts installed
  # below (the shim's distribution has the new one's name and is replaced by the install itself).
  if .venv/bin/python -I -c 'import importlib.metadata as m; m.distribution("lerobot_formation")' 2>/dev/null; then
    .venv/bin/python -m pip uninstall -q -y lerobot_formation 2>&1 | quiet_pip || true
    echo "[setup] the earlier layout's distribution lerobot_formation uninstalled (the project is now one: lerobot_env_formation)"
  fi
  .venv/bin/python -m pip install -q -e '.[dev]' 2>&1 | quiet_pip || true
  stage_done "LeRobot $(.venv/bin/python -c 'import importlib.metadata as m; print(m.version("lerobot"))' 2>/dev/null || echo '?') + lerobot_formation installed" "$start"
  .venv/bin/python -I -c 'import lerobot_formation, lerobot_env_formation, gym_formation, lerobot, torch' || { echo "error: install failed" >&2; exit 1; }
  echo "$want" > "$stamp"
}

cmd="${1:-}"
shift || true
case "$cmd" in
  setup) setup ;;
  demo)
    setup
    .venv/bin/python -m lerobot_formation.bench.demo "$@"
    ;;
  test)
    setup
    # Python writes its bytecode caches (git-ignored __pycache__/) during the tests even where the
    # environment says not to: the tests start many fresh interpreters, and each would compile the
    # project's modules (and pytest rewrite every test module) again.
    unset PYTHONDONTWRITEBYTECODE
    .venv/bin/ruff check .
    .venv/bin/ruff format --check .
    # Two workers (pytest-xdist), each on one thread (OMP_NUM_THREADS above; tests/conftest.py sets
    # torch's); --dist loadgroup keeps the tests that share a module's fixture on one worker
    # (tests/conftest.py marks them). The 25 slowest tests after the summary (-rfE: failures and
    # errors in it even under -q).
    .venv/bin/python -m pytest -n "${LEROBOT_FORMATION_TEST_WORKERS:-2}" --dist loadgroup --durations=25 -rfE "$@"
    ;;
  -h|--help)
    echo "usage: scripts/run.sh {demo|test|setup} [args]"
    echo
    # the comment at the top of this file, up to the first line of code
    awk 'NR > 1 && /^#/ { sub(/^# ?/, ""); print; next } NR > 1 { exit }' scripts/run.sh
    ;;
  *) echo "usage: scripts/run.sh {demo|test|setup} [args] (--help: what each does)" >&2; exit 2 ;;
esac
