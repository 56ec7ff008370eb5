#!/usr/bin/env bash
# nerfexp on a CUDA GPU, in one run of at most 8 minutes (docs/acceleration.md, "On a GPU"):
#   1. the machine: GPU, driver, torch, CUDA (benchmarks/gpu/gpu_check_report.py machine);
#   2. the device-independent tests on the GPU: pytest -m on_device with NERFEXP_TEST_DEVICE=cuda (every test that
#      takes the `device` fixture of tests/conftest.py, and the GPU's precision rule);
#   3. training steps timed by benchmarks/profiles/step_profile.py on the GPU, one process per variant: the paper's model
#      (scale=paper, precision auto), the same with the occupancy grid (acceleration=occupancy), the fast preset
#      (experiment=fast) and the fast preset at the paper's batch (experiment=fast scale=paper);
#   4. OUT/gpu_check.json and OUT/gpu_check.md (benchmarks/gpu/gpu_check_report.py summary), the whole log in
#      OUT/gpu_check.log, and the summary printed.
# Each stage runs under `timeout` (at most 460 s together); one that fails or times out is recorded, and the others
# still run.
#
# What it expects there: python3 with torch (a CUDA build), Lightning, pytest and pytest-xdist, hypothesis, numpy,
# scipy, scikit-image, imageio, matplotlib, tensorboard, markdown, tqdm, pyyaml, fsspec (a machine without network:
# the device machines' image has them). What such an image lacks, Hydra and OmegaConf, comes as wheels in .whl/
# (made here first with --prepare, where the package registry is reached) and is installed into /tmp, not into the
# machine's Python. nerfexp itself runs from src/ (PYTHONPATH): nothing is installed.
#
#   bash benchmarks/gpu/gpu_check.sh --prepare            # here, once: the wheels into .whl/ (git ignores it)
#   OUT=DIR bash benchmarks/gpu/gpu_check.sh              # on the GPU machine (its device tool sets OUT)
#   bash benchmarks/gpu/gpu_check.sh --dry-run            # here, on the CPU, tiny sizes: every stage's commands start
set -u -o pipefail
cd "$(dirname "$0")/../.." || exit 2
ROOT=$PWD
WHEELS=$ROOT/.whl
MODE=${1:-gpu}
case $MODE in
  gpu | --dry-run | --prepare) ;;
  *) echo "usage: OUT=DIR bash benchmarks/gpu/gpu_check.sh [--dry-run | --prepare]" >&2; exit 2 ;;
esac

if [ "$MODE" = --prepare ]; then
  # Hydra and OmegaConf at the versions installed here (pure Python wheels; antlr4's runtime is a source release,
  # built into a wheel here)
  versions=$(python3 -c 'import importlib.metadata as m; print(*(f"{n}=={m.version(n)}" for n in
    ("hydra-core", "omegaconf", "antlr4-python3-runtime")))') || exit 1
  rm -rf "$WHEELS" && mkdir -p "$WHEELS" || exit 1
  read -r hydra omegaconf antlr <<<"$versions"
  python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux2014_x86_64 -d "$WHEELS" "$hydra" "$omegaconf" || exit 1
  python3 -m pip wheel -q --no-deps -w "$WHEELS" "$antlr" || exit 1
  ls "$WHEELS"
  exit 0
fi

if [ "$MODE" = --dry-run ]; then
  OUT=${OUT:-$(mktemp -d)}
  export NERFEXP_TEST_DEVICE=cpu
  ACCELERATOR=cpu
  STEPS=(--steps 6 --window 3 --profile 2)  # a start of each variant, not a measurement
  SHRINK=(scale.batch_rays=64 scale.image_size=16)
  TESTS=(tests/nerf/test_quadrature.py tests/nerf/test_volume_renderer.py)
else
  : "${OUT:?set OUT to the folder that the figures go to}"
  export NERFEXP_TEST_DEVICE=cuda
  ACCELERATOR=gpu
  # past the occupancy grid's warm-up (256 steps: every cell re-evaluated at each update), the last 100 timed
  STEPS=(--steps 400 --window 100 --profile 10)
  SHRINK=(scale.image_size=100)  # the built-in scene made at 100 x 100 (400: minutes); a step draws random rays
  TESTS=(tests/nerf tests/training/test_optimizers.py tests/training/test_precision.py)
fi
mkdir -p "$OUT" || exit 2
WORK=$(mktemp -d)
LOG=$OUT/gpu_check.log
: >"$WORK/stages.tsv"
export PYTHONUNBUFFERED=1

# stage NAME SECONDS COMMAND...: runs COMMAND under timeout, output to the log, its status to stages.tsv
stage() {
  local name=$1 limit=$2 started status
  shift 2
  started=$(date +%s)
  echo "== $name (at most ${limit} s): $*" | tee -a "$LOG"
  timeout --kill-after=10 "$limit" "$@" >>"$LOG" 2>&1
  status=$?
  printf '%s\t%s\t%s\n' "$name" "$status" "$(($(date +%s) - started))" >>"$WORK/stages.tsv"
  echo "   exit $status after $(($(date +%s) - started)) s" | tee -a "$LOG"
  return 0
}

SITE=
if [ "$MODE" = gpu ] && compgen -G "$WHEELS/*.whl" >/dev/null; then
  stage wheels 30 python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target "$WORK/site" "$WHEELS"/*.whl
  SITE=$WORK/site:
fi
export PYTHONPATH=$SITE$ROOT/src
stage imports 30 python3 -c 'import torch, lightning, hydra, omegaconf, nerfexp.training.module'
stage machine 30 python3 benchmarks/gpu/gpu_check_report.py machine "$WORK/machine.json"
# the CPU kernels are not what runs on a GPU (its tensors take the torch path): not built here
stage tests 120 env NERFEXP_KERNELS=off python3 -m pytest -q -p no:randomly -p no:cacheprovider -m on_device \
  --junitxml="$WORK/tests.xml" "${TESTS[@]}"

# variant SECONDS NAME OVERRIDES...: one variant's training steps, in a process of its own (its file numbered in
# the order run, which the summary keeps)
VARIANTS=0
variant() {
  local limit=$1 name=$2
  shift 2
  VARIANTS=$((VARIANTS + 1))
  stage "steps: $name" "$limit" python3 benchmarks/profiles/step_profile.py "${STEPS[@]}" --out "$WORK/step_$VARIANTS" \
    --variant "$name" "$@" "trainer.accelerator=$ACCELERATOR" "${SHRINK[@]}"
}
variant 75 "paper" scale=paper
variant 75 "paper, occupancy grid" scale=paper acceleration=occupancy
variant 50 "fast" experiment=fast
variant 50 "fast, paper batch" experiment=fast scale=paper

python3 benchmarks/gpu/gpu_check_report.py summary "$WORK" "$OUT" | tee -a "$LOG"
rm -rf "$WORK"
