#!/usr/bin/env bash
# From-nothing, idempotent set-up of deepprompt_ros in a virtual environment.
#
#   bash tools/setup.sh [--check] [VENV]     (default VENV: .venv; `make setup` runs this)
#
# Steps (each skipped when its inputs did not change since its last success):
#   1. create VENV with Python 3.11 (PYTHON=/path/to/python3.11 to choose one);
#   2. pip install -r requirements.txt        (stamp: sha256 of requirements.txt);
#   3. rewrite the wheels' CMake include paths to this interpreter's
#      (tools/fix_cmake_paths.py; always run, idempotent, < 1 s);
#   4. build the interface package msg_defs/ (deepprompt_msgs) with plain CMake,
#      installed into the VENV prefix; build dir build/deepprompt_msgs
#      (stamp: sha256 of msg_defs/ and of requirements.txt);
#   5. pip install -e . --no-deps, so `import deepprompt_ros` works from anywhere
#      and follows the sources (stamp: sha256 of setup.py and setup.cfg);
#   6. ROS install layout (tools/install_ros_layout.py; always run): launchers in
#      VENV/lib/deepprompt_ros/, share/deepprompt_ros/{package.xml,config,models,launch,urdf},
#      ament index marker. `ros2 run deepprompt_ros <exe>` then finds them with
#      VENV on AMENT_PREFIX_PATH.
# --check: change nothing; list what is out of date and exit 1 if anything is.
# Stamps live in VENV/.setup-stamps/; delete that folder (or VENV) to force a redo.
# A lock (build/setup.lock) serialises concurrent runs.
set -euo pipefail

CHECK=0
if [[ "${1:-}" == "--check" ]]; then CHECK=1; shift; fi
VENV_ARG="${1:-.venv}"
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
case "$VENV_ARG" in
  /*) VENV="$VENV_ARG" ;;
  *)  VENV="$PWD/$VENV_ARG" ;;   # relative to the caller's directory
esac
VENV="${VENV%/}"
cd "$ROOT"
PY="$VENV/bin/python"
STAMPS="$VENV/.setup-stamps"
BUILD_DIR="$ROOT/build/deepprompt_msgs"
JOBS="${JOBS:-$(nproc 2>/dev/null || echo 2)}"
T0=$SECONDS
STALE=()

say() { printf '[setup %3ds] %s\n' "$((SECONDS - T0))" "$*"; }
die() { printf '[setup] ERROR: %s\n' "$*" >&2; exit 1; }
stale() { STALE+=("$1"); say "out of date: $1"; }

# sha256 over the named files/directories (relative paths and contents).
hash_paths() {
  local p
  for p in "$@"; do
    if [[ -d "$p" ]]; then
      find "$p" -type f ! -name '*.pyc' ! -path '*/__pycache__/*' -print0 | LC_ALL=C sort -z \
        | xargs -0 -r sha256sum
    elif [[ -f "$p" ]]; then
      sha256sum "$p"
    else
      echo "missing $p"
    fi
  done | sha256sum | cut -d' ' -f1
}
stamp_matches() { [[ -f "$STAMPS/$1" && "$(cat "$STAMPS/$1")" == "$2" ]]; }
write_stamp() { mkdir -p "$STAMPS"; printf '%s\n' "$2" > "$STAMPS/$1"; }

if [[ "$CHECK" == 0 ]]; then
  mkdir -p "$ROOT/build"
  exec 9>"$ROOT/build/setup.lock"
  if ! flock -n 9; then
    say "another setup run holds build/setup.lock: waiting for it"
    flock 9
  fi
fi

# ---------------------------------------------------------------- 1. venv
if [[ ! -x "$PY" ]]; then
  [[ "$CHECK" == 1 ]] && { stale "no virtual environment at $VENV"; say "run: bash tools/setup.sh $VENV_ARG"; exit 1; }
  BASE_PY="${PYTHON:-}"
  if [[ -z "$BASE_PY" ]]; then
    if command -v python3.11 >/dev/null 2>&1; then BASE_PY=python3.11; else BASE_PY=python3; fi
  fi
  command -v "$BASE_PY" >/dev/null 2>&1 \
    || die "no '$BASE_PY' on PATH; install Python 3.11 or set PYTHON=/path/to/python3.11"
  BASE_VER="$("$BASE_PY" -c 'import sys; print("%d.%d" % sys.version_info[:2])')"
  [[ "$BASE_VER" == "3.11" ]] \
    || die "$BASE_PY is Python $BASE_VER; the pinned ROS 2 Jazzy wheels need Python 3.11 (set PYTHON=/path/to/python3.11)"
  say "creating virtual environment $VENV with $(command -v "$BASE_PY") (Python $BASE_VER)"
  "$BASE_PY" -m venv "$VENV"
else
  say "virtual environment $VENV exists"
fi
VENV_VER="$("$PY" -c 'import sys; print("%d.%d" % sys.version_info[:2])')"
[[ "$VENV_VER" == "3.11" ]] || die "$PY is Python $VENV_VER; expected 3.11 (remove $VENV to recreate it)"

# ---------------------------------------------------------------- 2. requirements
REQ_HASH="$(hash_paths requirements.txt)"
if stamp_matches requirements "$REQ_HASH"; then
  say "requirements.txt unchanged since the last install: skipping pip"
elif [[ "$CHECK" == 1 ]]; then
  stale "requirements.txt changed since the last install (or never installed)"
else
  say "installing requirements.txt into $VENV (a cold install takes a few minutes)"
  mkdir -p "$STAMPS"
  # full pip output goes to a log; progress lines are echoed
  "$PY" -m pip install --disable-pip-version-check --progress-bar off -r requirements.txt 2>&1 \
    | tee "$STAMPS/pip-install.log" \
    | { grep --line-buffered -E '^(Installing collected|Successfully installed|ERROR|error)' | cut -c1-150 || true; } \
    || { tail -n 30 "$STAMPS/pip-install.log" >&2; die "pip install -r requirements.txt failed; full log: $STAMPS/pip-install.log"; }
  write_stamp requirements "$REQ_HASH"
  say "requirements installed"
fi

# ---------------------------------------------------------------- 3. CMake paths
if [[ "$CHECK" == 1 ]]; then
  "$PY" tools/fix_cmake_paths.py --check "$VENV" >/dev/null 2>&1 \
    || stale "wheel CMake files still name the build machine's include paths"
else
  FIX_OUT="$("$PY" tools/fix_cmake_paths.py "$VENV")" || die "rewriting the CMake include paths failed (see above)"
  say "$FIX_OUT"
fi

# ---------------------------------------------------------------- 4. interfaces
MSG_HASH="$(hash_paths msg_defs)-$REQ_HASH"
MSG_INSTALLED=0
if [[ -f "$VENV/share/deepprompt_msgs/package.xml" \
      && -f "$VENV/share/ament_index/resource_index/packages/deepprompt_msgs" ]] \
   && compgen -G "$VENV/lib/python3.11/site-packages/deepprompt_msgs/deepprompt_msgs_s__rosidl_typesupport_c*.so" >/dev/null; then
  MSG_INSTALLED=1
fi
if [[ "$MSG_INSTALLED" == 1 ]] && stamp_matches msg_defs "$MSG_HASH"; then
  say "msg_defs/ unchanged: deepprompt_msgs is up to date"
elif [[ "$CHECK" == 1 ]]; then
  stale "deepprompt_msgs not built from the current msg_defs/ and requirements.txt"
else
  say "building deepprompt_msgs (msg_defs/) into $VENV with CMake, $JOBS jobs; log: $BUILD_DIR/build.log"
  rm -rf "$BUILD_DIR"   # clean build: the generated code must match the installed wheels
  mkdir -p "$BUILD_DIR"
  (
    export AMENT_PREFIX_PATH="$VENV"   # rosidl finds its typesupports through the ament index
    export CMAKE_PREFIX_PATH="$VENV"
    cmake -S msg_defs -B "$BUILD_DIR" \
      -DCMAKE_PREFIX_PATH="$VENV" -DCMAKE_INSTALL_PREFIX="$VENV" \
      -DPython3_EXECUTABLE="$PY" -DBUILD_TESTING=OFF
    cmake --build "$BUILD_DIR" --target install --parallel "$JOBS"
  ) > "$BUILD_DIR/build.log" 2>&1 || {
    tail -n 40 "$BUILD_DIR/build.log" >&2
    die "building msg_defs failed; full log: $BUILD_DIR/build.log"
  }
  write_stamp msg_defs "$MSG_HASH"
  say "deepprompt_msgs installed"
fi

# ---------------------------------------------------------------- 5. deepprompt_ros
PKG_HASH="$(hash_paths setup.py setup.cfg)"
# up to date = same setup files AND the installed import hook maps to this checkout
if stamp_matches package "$PKG_HASH" && (cd / && "$PY" - "$ROOT" <<'EOF' 2>/dev/null)
import importlib.metadata, importlib.util, os, sys
importlib.metadata.distribution("deepprompt_ros")
spec = importlib.util.find_spec("deepprompt_ros")
where = [os.path.realpath(p) for p in (spec.submodule_search_locations or [])]
sys.exit(0 if os.path.realpath(os.path.join(sys.argv[1], "deepprompt_ros")) in where else 1)
EOF
then
  say "deepprompt_ros editable install is up to date"
elif [[ "$CHECK" == 1 ]]; then
  stale "deepprompt_ros is not installed (editable) from this checkout's setup.py/setup.cfg"
else
  say "installing deepprompt_ros (editable) into $VENV"
  mkdir -p "$STAMPS"
  "$PY" -m pip install --disable-pip-version-check --no-deps --no-build-isolation -e "$ROOT" \
    > "$STAMPS/pip-editable.log" 2>&1 \
    || { tail -n 30 "$STAMPS/pip-editable.log" >&2; die "pip install -e . failed; full log: $STAMPS/pip-editable.log"; }
  write_stamp package "$PKG_HASH"
fi

# ---------------------------------------------------------------- 6. ROS layout
if [[ "$CHECK" == 1 ]]; then
  LAYOUT_OUT="$("$PY" tools/install_ros_layout.py --check --prefix "$VENV" --source "$ROOT" 2>&1)" \
    || stale "ROS install layout: $LAYOUT_OUT"
else
  LAYOUT_OUT="$("$PY" tools/install_ros_layout.py --prefix "$VENV" --source "$ROOT")" \
    || die "creating the ROS install layout failed (see above)"
  say "$LAYOUT_OUT"
fi

if [[ "$CHECK" == 1 ]]; then
  if (( ${#STALE[@]} )); then
    say "${#STALE[@]} step(s) out of date: run bash tools/setup.sh $VENV_ARG (or make setup)"
    exit 1
  fi
  say "everything is up to date"
  exit 0
fi
say "done: use $PY  (ros2 run finds the package with AMENT_PREFIX_PATH=$VENV)"
