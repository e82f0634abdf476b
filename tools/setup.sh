#!/usr/bin/env bash
# The one set-up step for a fresh Debian machine (no ROS installed):
#   1. apt prerequisites, only if missing (cmake, g++, ninja, Python headers and venv, iproute2);
#   2. .venv with requirements/lock.txt: the whole closure, hashed (tools/lock.sh writes it), the
#      same in every path (with or without --test, with or without ../shared): the ROS 2 Kilted
#      wheels, the interface build tools, the dev tools, colcon and the PyPI parts of the ROS 2
#      command line, pip and setuptools themselves; pip refuses any file whose hash it does not list;
#   3. the packml_interfaces wheel, built from msg_defs/ once and kept in .cache/wheels/;
#   4. packml_ros2 itself, editable, and the venv made an ament prefix (tools/ament_prefix.py:
#      lib/packml_ros2/<executable>, share/packml_ros2/...), so `ros2 run` / `ros2 launch` find it;
#   5. with --test: what only the tests need (Debian's chromium for the HMI browser tests, Debian's
#      mosquitto broker and clients for the MQTT tests, the npm packages of the independent OPC UA
#      client in test/opcua_client/);
#   6. with --test, when ../shared/vendor/ros2-tools exists: the real ROS 2 command line (ros2),
#      launch and launch_ros built from its sources (composition_interfaces like msg_defs/); the
#      wheels are kept in .cache/wheels/. Like packml_interfaces and packml_ros2 they are built here
#      and installed --no-deps, so they are not in the lock (their dependencies are).
# Each step is skipped when its inputs did not change, so a second run takes seconds.
set -euo pipefail
for_tests=0
[ "${1:-}" = "--test" ] && for_tests=1
cd "$(dirname "${BASH_SOURCE[0]}")/.."

VENV=${VENV:-.venv}
PYTHON=${PYTHON:-python3}
CACHE=.cache/wheels
say() { printf '\033[1m[setup]\033[0m %s\n' "$*"; }
digest() { sha256sum "$@" | sha256sum | cut -c1-16; }

# --- 1. system packages -------------------------------------------------------------------------
missing=()
command -v cmake >/dev/null || missing+=(cmake)
command -v g++ >/dev/null || missing+=(g++)
command -v ninja >/dev/null || missing+=(ninja-build)
command -v ip >/dev/null || missing+=(iproute2)
if ((for_tests)); then
  command -v chromium >/dev/null || missing+=(chromium)
  command -v node >/dev/null || missing+=(nodejs)
  command -v npm >/dev/null || missing+=(npm)
  command -v faketime >/dev/null || missing+=(faketime)  # wall-clock steps (test_clock_steps)
  [ -x /usr/sbin/mosquitto ] || missing+=(mosquitto)  # the MQTT broker of the Sparkplug tests
  command -v mosquitto_sub >/dev/null || missing+=(mosquitto-clients)
fi
if command -v "$PYTHON" >/dev/null; then
  "$PYTHON" - <<'PY' || missing+=(python3-dev)
import os, sys, sysconfig
sys.exit(0 if os.path.exists(os.path.join(sysconfig.get_paths()["include"], "Python.h")) else 1)
PY
  "$PYTHON" -c 'import ensurepip, venv' 2>/dev/null || missing+=(python3-venv)
else
  missing+=(python3 python3-dev python3-venv)
fi
if ((${#missing[@]})); then
  say "installing Debian packages: ${missing[*]}"
  sudo=""
  [ "$(id -u)" = 0 ] || sudo=sudo
  $sudo apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends "${missing[@]}"
fi

# --- 2. the virtual environment -----------------------------------------------------------------
if [ ! -x "$VENV/bin/python" ]; then
  say "creating $VENV"
  "$PYTHON" -m venv "$VENV"
fi
pip=("$VENV/bin/python" -m pip --disable-pip-version-check -q)
deps_key=$(digest requirements/lock.txt setup.py package.xml)
if [ "$(cat "$VENV/.packml-deps" 2>/dev/null)" != "$deps_key" ]; then
  say "installing requirements/lock.txt into $VENV (every package pinned and hashed)"
  # --no-deps: the lock is the whole closure (pip's resolver would take a dependency that asks for
  # an extra, coverage[toml], as unpinned); pip check then proves nothing is missing from it
  "${pip[@]}" install --require-hashes --no-deps -r requirements/lock.txt
  "$VENV/bin/python" tools/lock_check.py --pip-check
  # what an older lock installed and this one does not have (pip freeze must equal the lock)
  mapfile -t stale < <("$VENV/bin/python" tools/lock_check.py --stale)
  if ((${#stale[@]})); then "${pip[@]}" uninstall -y "${stale[@]}"; fi
  echo "$deps_key" > "$VENV/.packml-deps"
  rm -f "$VENV/.packml-self"
fi

# --- 3. packml_interfaces -----------------------------------------------------------------------
msg_key=$(digest $(find msg_defs -path msg_defs/build -prune -o -type f \( -name '*.msg' -o -name '*.srv' \
  -o -name CMakeLists.txt -o -name '*.cmake' -o -name package.xml -o -name pyproject.toml \) -print | LC_ALL=C sort) \
  requirements/ros.txt requirements/build.txt)
if [ "$(cat "$VENV/.packml-interfaces" 2>/dev/null)" != "$msg_key" ]; then
  wheel_dir="$CACHE/packml_interfaces-$msg_key"
  if ! ls "$wheel_dir"/*.whl >/dev/null 2>&1; then
    say "building packml_interfaces from msg_defs/ (about 1-2 minutes, once)"
    rm -rf msg_defs/build "$wheel_dir.tmp"
    "${pip[@]}" wheel --no-deps --no-build-isolation -w "$wheel_dir.tmp" ./msg_defs
    rm -rf msg_defs/build
    mv "$wheel_dir.tmp" "$wheel_dir"
  fi
  say "installing $(basename "$wheel_dir"/*.whl)"
  "${pip[@]}" install --no-deps --force-reinstall "$wheel_dir"/*.whl
  echo "$msg_key" > "$VENV/.packml-interfaces"
fi

# --- 4. packml_ros2, editable ---------------------------------------------------------------------
if [ "$(cat "$VENV/.packml-self" 2>/dev/null)" != "$deps_key" ]; then
  say "installing packml_ros2 (editable)"
  "${pip[@]}" install --no-build-isolation --no-deps -e .
  echo "$deps_key" > "$VENV/.packml-self"
fi
prefix_key=$(digest setup.py setup.cfg tools/ament_prefix.py <(ls launch config))
if [ "$(cat "$VENV/.packml-prefix" 2>/dev/null)" != "$prefix_key" ]; then
  "$VENV/bin/python" tools/ament_prefix.py "$VENV" >/dev/null
  echo "$prefix_key" > "$VENV/.packml-prefix"
fi
# --- 5. test-only pieces ------------------------------------------------------------------------------
if ((for_tests)) && [ -f test/opcua_client/package-lock.json ]; then
  npm_key=$(digest test/opcua_client/package.json test/opcua_client/package-lock.json)
  if [ "$(cat test/opcua_client/node_modules/.packml-npm 2>/dev/null)" != "$npm_key" ]; then
    say "installing the OPC UA test client (npm ci in test/opcua_client)"
    (cd test/opcua_client && npm ci --no-audit --no-fund --loglevel=error)
    echo "$npm_key" > test/opcua_client/node_modules/.packml-npm
  fi
fi
# --- 6. the real ros2 CLI, launch, launch_ros and colcon (tests only) --------------------------------
vendor=../shared/vendor/ros2-tools
if ((for_tests)) && [ -d "$vendor" ]; then
  tools_key=$(digest "$vendor"/*.tar.gz requirements/lock.txt \
    tools/ros2-tools/* msg_defs/cmake/ros_wheels.cmake)
  if [ "$(cat "$VENV/.packml-ros2-tools" 2>/dev/null)" != "$tools_key" ]; then
    say "installing the ROS 2 command line, launch and launch_ros ($vendor)"
    wheel_dir="$CACHE/ros2-tools-$tools_key"
    if ! ls "$wheel_dir"/*.whl >/dev/null 2>&1; then
      say "building ros2cli, launch, launch_ros, rosidl_runtime_py and composition_interfaces (once)"
      src=.cache/ros2-tools-src
      rm -rf "$src" "$wheel_dir.tmp"
      mkdir -p "$src"
      for tarball in "$vendor"/*.tar.gz; do tar -xzf "$tarball" -C "$src"; done
      interfaces="$src/rcl_interfaces/composition_interfaces"
      cp tools/ros2-tools/composition_interfaces.pyproject.toml "$interfaces/pyproject.toml"
      log=.cache/ros2-tools-build.log
      # Pure Python packages: their install_requires name ROS packages (ament_index_python) that
      # exist here only as ros-* wheels, hence --no-deps (the real dependencies are above).
      mapfile -t python_packages < <(find "$src" -name setup.py -printf '%h\n' | LC_ALL=C sort)
      { "${pip[@]}" wheel --no-deps --no-build-isolation -w "$wheel_dir.tmp" \
          -C cmake.define.CMAKE_PROJECT_INCLUDE="$PWD/msg_defs/cmake/ros_wheels.cmake" \
          -C cmake.define.BUILD_TESTING=OFF "$interfaces" &&
        "${pip[@]}" wheel --no-deps --no-build-isolation -w "$wheel_dir.tmp" "${python_packages[@]}"
      } >"$log" 2>&1 || { cat "$log"; exit 1; }
      rm -rf "$src" "$log"
      mv "$wheel_dir.tmp" "$wheel_dir"
    fi
    "${pip[@]}" install --no-deps --force-reinstall "$wheel_dir"/*.whl
    echo "$tools_key" > "$VENV/.packml-ros2-tools"
  fi
elif ((for_tests)); then
  say "no $vendor here: the tests of ros2, ros2 launch and colcon will be skipped"
fi
say "ready: $VENV ($("$VENV/bin/python" -c 'import rclpy, packml_interfaces, packml_ros2; print("rclpy, packml_interfaces, packml_ros2 import")'))"
