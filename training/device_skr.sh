#!/usr/bin/env bash
# SKR continued on a lent GPU, in one call of the device tool (README, Training).
#
#   bash training/device_skr.sh SECONDS [--set KEY=VALUE ...]
#
# run there with data/pack.npz carried (python -m training.data pack, here) and a timeout
# that leaves about 150 s beyond SECONDS. It checks the GPU against the CPU
# (tests/test_online.py's CUDA test), builds the T-pose frames from the pack, then trains SKR
# from the shipped weights on fresh frames for SECONDS of wall clock (--stage-seconds: the
# schedule is cut to what fits and still ends) and writes into $OUT: device.txt, tests.log,
# and skr/ (weights.npz, skr.pt, skr.csv, skr.png, recipe.json). Extra arguments go to
# training.train. The refiner and the denoiser then retrain here, on the CPU, from builds.
# DEVICE=cpu rehearses it all on a machine without a GPU (the CUDA test then skips).
set -euo pipefail
seconds=${1:?usage: bash training/device_skr.sh SECONDS [--set KEY=VALUE ...]}
shift
out=${OUT:?OUT must name the folder that comes back}
device=${DEVICE:-cuda}
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1
test -f data/pack.npz || { echo "data/pack.npz is missing: carry it (python -m training.data pack)" >&2; exit 2; }

if [ "$device" = cuda ]; then
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv > "$out/device.txt"
else
    echo "rehearsal on $device" > "$out/device.txt"
fi
python3 -c "import numba, numpy, torch; print('torch', torch.__version__, 'numpy',
numpy.__version__, 'numba', numba.__version__, 'cuda', torch.cuda.is_available())" \
    >> "$out/device.txt"
cat "$out/device.txt"
python3 -m pytest -q -p no:cacheprovider tests/test_online.py -k cuda 2>&1 | tee "$out/tests.log"
python3 -m training.data build --pack data/pack.npz --out /tmp/data --only skr_tpose
python3 -m training.train skr --recipe training/recipes/cpu_continue.json \
    --init minretarget/data/default_weights.npz --pack data/pack.npz --data /tmp/data \
    --out "$out/skr" --device "$device" --stage-seconds "$seconds" --set skr.steps=1000000 "$@"
