#!/usr/bin/env bash
# install.sh: set up n2d on a fresh Debian 12 / Ubuntu 22.04+ machine, idempotently.
#
#   ./install.sh            apt libraries (if missing), .venv, pinned Python deps, the interface packages
#                           (vision_msgs, tf2_msgs, n2d_interfaces: CMake, against the ROS 2 Jazzy wheels) and
#                           the n2d packages (editable)
#
# A second run checks stamps and finishes in seconds. Environment:
#   N2D_VENV   where the virtual environment goes (default: .venv in the repo)
#   PYTHON     the interpreter to build it from (default: python3; must be 3.11, bpy's wheel needs it)
set -euo pipefail
cd "$(dirname "$(readlink -f "$0")")"
ROOT=$PWD
VENV=${N2D_VENV:-$ROOT/.venv}
PYTHON=${PYTHON:-python3}
PACKAGES=(n2d_common n2d_blender n2d_capture n2d_sim n2d_reconstruct n2d_dataset n2d_dope n2d)
say() { printf '\033[1m[install]\033[0m %s\n' "$*"; }

# --- 1. system libraries: bpy's X/GL libraries, the interface build tools --------------------------
APT_PKGS=(libx11-6 libxrender1 libxfixes3 libxi6 libxkbcommon0 libsm6 libxext6 libgl1 libegl1
          cmake ninja-build g++ libtcmalloc-minimal4)
"$PYTHON" - <<'EOF' || APT_PKGS+=(python3-dev python3-venv)
import os, sys, sysconfig
sys.exit(0 if os.path.exists(os.path.join(sysconfig.get_paths()["include"], "Python.h")) else 1)
EOF
missing=()
for p in "${APT_PKGS[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q 'install ok installed' || missing+=("$p")
done
if ((${#missing[@]})); then
  say "apt: installing ${missing[*]}"
  SUDO=; [ "$(id -u)" -eq 0 ] || SUDO=sudo
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
fi

# --- 2. the virtual environment ------------------------------------------------------------------------
pyver=$("$PYTHON" -c 'import sys; print("%d.%d" % sys.version_info[:2])')
if [ "$pyver" != "3.11" ]; then
  echo "install.sh: $PYTHON is Python $pyver, but bpy==5.0.1 ships wheels for 3.11 only." >&2
  echo "  hint: run with PYTHON=/path/to/python3.11 ./install.sh" >&2
  exit 1
fi
[ -x "$VENV/bin/python" ] || { say "creating $VENV"; "$PYTHON" -m venv "$VENV"; }
PY=$VENV/bin/python
stamp() { sha256sum "$@" | sha256sum | cut -c1-16; }

# --- 3. Python dependencies (torch first: the CPU wheel, then everything else pinned) ------------------
deps_stamp=$(stamp requirements.txt requirements-base.txt constraints.txt install.sh)
if [ "$(cat "$VENV/.n2d-deps" 2>/dev/null)" != "$deps_stamp" ]; then
  say "pip: installing pinned dependencies (first run: a few minutes)"
  "$PY" -m pip install -q --upgrade 'pip>=24' 'setuptools<80' wheel
  "$PY" -m pip install -q torch==2.13.0
  "$PY" -m pip install -q -r requirements.txt -c constraints.txt
  # The ROS wheels' exported CMake files hard-code the build machine's interpreter paths.
  PYINC=$("$PY" -c "import sysconfig; print(sysconfig.get_paths()['include'])")
  NPINC=$("$PY" -c "import numpy; print(numpy.get_include())")
  { grep -rl '/opt/python/cp311-cp311/' "$VENV/share" --include='*.cmake' || true; } | xargs -r sed -i \
    -e "s#/opt/python/cp311-cp311/include/python3.11#$PYINC#g" \
    -e "s#/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include#$NPINC#g"
  # ament_index lookups (get_package_share_directory) need AMENT_PREFIX_PATH; point it at the venv.
  SITE=$("$PY" -c "import sysconfig; print(sysconfig.get_paths()['purelib'])")
  echo "import os, sys; os.environ.setdefault('AMENT_PREFIX_PATH', sys.prefix)" > "$SITE/n2d_ament_prefix.pth"
  echo "$deps_stamp" > "$VENV/.n2d-deps"
fi

# --- 4. interface packages: CMake builds against the Jazzy wheels, installed into the venv ---------------
# vision_msgs and tf2_msgs (the upstream names and fields; only where no ROS installation provides them), then
# n2d_interfaces.
build_interfaces() {  # NAME SOURCE_DIR
  local stamp_file="$VENV/.n2d-if-$1" stamp_value
  stamp_value=$(stamp $(find "$2" -type f | sort) "$VENV/.n2d-deps")
  [ "$(cat "$stamp_file" 2>/dev/null)" = "$stamp_value" ] && return 0
  say "building $1"
  export AMENT_PREFIX_PATH=$VENV
  # a clean build: rosidl's generated sources do not follow a removed interface in an incremental one
  rm -rf "build/$1"
  cmake -S "$2" -B "build/$1" -G Ninja -DCMAKE_PREFIX_PATH="$VENV" \
    -DCMAKE_INSTALL_PREFIX="$VENV" -DPython3_EXECUTABLE="$PY" -DBUILD_TESTING=OFF >/dev/null
  cmake --build "build/$1" -j"$(nproc)" >/dev/null
  cmake --install "build/$1" >/dev/null
  echo "$stamp_value" > "$stamp_file"
}
for pkg in vision_msgs tf2_msgs visualization_msgs; do
  if [ -f "$VENV/.n2d-if-$pkg" ] || ! "$PY" -c "import $pkg.msg" 2>/dev/null; then
    build_interfaces "$pkg" "interfaces/$pkg"
  fi
done
build_interfaces n2d_interfaces n2d_interfaces

# --- 5. the n2d packages, editable, with their ament index entries ----------------------------------------
pk_stamp=$(stamp $(for p in "${PACKAGES[@]}"; do echo "$p/setup.py" "$p/package.xml"; done) "$VENV/.n2d-deps")
if [ "$(cat "$VENV/.n2d-packages" 2>/dev/null)" != "$pk_stamp" ]; then
  say "installing the n2d packages (editable)"
  args=(); for p in "${PACKAGES[@]}"; do args+=(-e "./$p"); done
  # compat mode: path entries, so a regular package wins over the same-named source folder in the cwd
  "$PY" -m pip install -q --no-deps --no-build-isolation --config-settings editable_mode=compat \
    "${args[@]}" >"$VENV/.n2d-pip.log" 2>&1 || { cat "$VENV/.n2d-pip.log" >&2; exit 1; }
  # pip's editable installs skip data_files; register what `ros2 launch` and ament_index look up.
  for p in "${PACKAGES[@]}"; do
    mkdir -p "$VENV/share/ament_index/resource_index/packages" "$VENV/share/$p"
    touch "$VENV/share/ament_index/resource_index/packages/$p"
    ln -sfn "$ROOT/$p/package.xml" "$VENV/share/$p/package.xml"
  done
  ln -sfn "$ROOT/n2d/launch" "$VENV/share/n2d/launch"
  echo "$pk_stamp" > "$VENV/.n2d-packages"
fi

"$PY" -c "import n2d_interfaces.action, vision_msgs.msg, tf2_msgs.msg, visualization_msgs.msg, rclpy, bpy, cv2, torch, dynamixel_sdk, n2d.cli" \
  || { echo "install.sh: the environment does not import; delete $VENV and run again" >&2; exit 1; }
say "ready: $VENV/bin/n2d"
