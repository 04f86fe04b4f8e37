#!/usr/bin/env bash
# Downloads, on a machine with PyPI, the wheels that a GPU machine without network needs to run
# benchmarks/gpu_check.sh: this package's dependencies that a stock CUDA PyTorch image lacks (torchrl, tensordict,
# Hydra, Gymnasium, MuJoCo and what they need), for the GPU machine's Python and platform, into .whl/ (git-ignored).
# gpu_check.sh installs them from there, offline, into a folder of its own and leaves the image's PyTorch alone.
#
#   bash benchmarks/gpu_wheels.sh                    # CPython 3.12, manylinux x86-64 (the default)
#   PY_VERSION=3.11 bash benchmarks/gpu_wheels.sh    # another Python
#
# Versions: torchrl and tensordict are this project's own pins (pyproject.toml); the rest are the versions its CPU
# install resolved when this list was written, except where that version has no wheel for a newer Python (orjson
# 3.8) or none at all (antlr4-python3-runtime 4.9.3, Hydra's pin: built here from its pure-Python source).
# MuJoCo's viewer packages (mujoco-studio and its web assets, 11 MB) are left out: `import mujoco` and the
# Gymnasium environments run without them.
set -euo pipefail
cd "$(dirname "$0")/.."
dest=.whl
py=${PY_VERSION:-3.12}
binary=(torchrl==0.14.1 tensordict==0.14.3 hoptorch==0.1.4 pyvers==0.2.3 orjson==3.10.18 importlib_metadata==10.2.0
        lazy-importer==0.1.0 hydra-core==1.3.8 omegaconf==2.3.1 gymnasium==1.4.0 Farama-Notifications==0.0.6
        mujoco==4.0.1 mujoco-core==4.0.1 glfw==2.11.0 PyOpenGL==3.1.10)
source_only=(antlr4-python3-runtime==4.9.3)
mkdir -p "$dest"
platforms=()
for p in manylinux_2_28_x86_64 manylinux_2_27_x86_64 manylinux_2_17_x86_64 manylinux2014_x86_64 manylinux1_x86_64 any; do
  platforms+=(--platform "$p")
done
python3 -m pip download --quiet --no-deps --only-binary=:all: --python-version "$py" --implementation cp \
  "${platforms[@]}" -d "$dest" "${binary[@]}"
python3 -m pip wheel --quiet --no-deps -w "$dest" "${source_only[@]}"
n=$(find "$dest" -type f -name '*.whl' | wc -l)
if [ "$n" -ne $(( ${#binary[@]} + ${#source_only[@]} )) ]; then
  echo "gpu_wheels.sh: $dest holds $n wheels, expected $(( ${#binary[@]} + ${#source_only[@]} )) (one version of each:" \
       "remove $dest and run again)" >&2
  exit 1
fi
echo "$dest: $n wheels, $(du -sh "$dest" | cut -f1); a device run carries it: carry=[\"$dest\"]"
