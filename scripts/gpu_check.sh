#!/usr/bin/env bash
# The GPU check (README, "Scaling out"): on a machine with one CUDA GPU, run the tests that need it (the
# simulator's CUDA values and gradients against the compiled CPU kernels, gradcheck on CUDA, EdgeConv on
# CUDA, a smoke training of both stages with trainer=gpu), then time the main job (conn at the paper's
# settings) with trainer=gpu and with the CPU trainer on the same machine. Logs go to OUT, the runs to
# OUT/run_gpu and OUT/run_default unless RUNS names another folder.
#   [PYTHON=python3] [RUNS=folder] bash scripts/gpu_check.sh OUT [overrides for both timed runs...]
set -euo pipefail
cd "$(dirname "$0")/.."
out=$(realpath -m "${1:?give an output folder for the logs}")
shift
python=${PYTHON:-.venv/bin/python}
mkdir -p "$out"
"$python" -c "import torch; assert torch.cuda.is_available(), 'no CUDA GPU here'; print(torch.__version__, \
torch.version.cuda, torch.cuda.get_device_name())" | tee "$out/device.txt"
"$python" -m pytest -q -o addopts="-ra -p no:cacheprovider" tests/test_simulator.py tests/test_model_math.py \
    tests/test_ddp.py -k "cuda or gpu" 2>&1 | tee "$out/gpu_tests.log"
runs=$(realpath -m "${RUNS:-$out}")
for trainer in gpu default; do
    start=$(date +%s)
    "$python" train.py trainer=$trainer trainer.progress_bar=false mlflow.enabled=false \
        "hydra.run.dir=$runs/run_$trainer" "$@" > "$out/train_$trainer.log" 2>&1 \
        || { tail -30 "$out/train_$trainer.log"; exit 1; }
    echo "trainer=$trainer: $(( $(date +%s) - start )) s for the whole command"
    tail -3 "$out/train_$trainer.log"
done
