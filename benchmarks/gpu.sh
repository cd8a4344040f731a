#!/usr/bin/env bash
# The GPU figures of benchmarks/README.md in one run on one GPU, at most 8 minutes, nothing downloaded:
#   1. batch-1 FPS of the Table I configs (B0 and B4 at 128x352, B4 at 256x704), fp32 / bf16 x eager /
#      torch.compile / CUDA graphs, model and model + decoding, as one Markdown table (benchmarks/fps.py);
#   2. training samples/s at batch 8, fp32 and bf16 (benchmarks/train_speed.py).
#
#   bash benchmarks/gpu.sh                      # on the GPU machine, from the repository root
#   DEVICE=cpu CONFIGS=configs/synthetic/tiny.yaml MODES=eager RUNS=1 TRAIN=0 bash benchmarks/gpu.sh  # its CPU check
#
# Settings (environment): DEVICE (cuda), RUNS (30 per cell), WARMUP (5), AMP ("none bf16"), MODES ("eager compile
# cuda_graphs"), CONFIGS (the three Table I rows), TRAIN (1: also the training table), BUDGET_S (480: the whole
# run; each part stops at its share and says so, the rows printed so far stay).
set -uo pipefail
cd "$(dirname "$0")/.."
DEVICE=${DEVICE:-cuda}
RUNS=${RUNS:-30}
WARMUP=${WARMUP:-5}
AMP=${AMP:-none bf16}
MODES=${MODES:-eager compile cuda_graphs}
CONFIGS=${CONFIGS:-configs/paper/table1_b0_lss_128x352.yaml configs/paper/table1_b4_lss_128x352.yaml configs/paper/table1_b4_lss_256x704.yaml}
TRAIN=${TRAIN:-1}
BUDGET_S=${BUDGET_S:-480}
case "$RUNS$WARMUP$BUDGET_S" in *[!0-9]*) echo "gpu.sh: error: RUNS, WARMUP and BUDGET_S must be whole numbers" >&2; exit 2;; esac
case "$TRAIN" in 0|1) ;; *) echo "gpu.sh: error: TRAIN must be 0 or 1, got $TRAIN" >&2; exit 2;; esac
fps_s=$(( TRAIN == 1 ? BUDGET_S * 3 / 4 : BUDGET_S ))

# shellcheck disable=SC2086  # the lists split into arguments on purpose
timeout "$fps_s" python3 benchmarks/fps.py --device "$DEVICE" --runs "$RUNS" --warmup "$WARMUP" --amp $AMP \
    --modes $MODES --configs $CONFIGS --markdown
rc=$?
if [ "$rc" = 124 ]; then echo "gpu.sh: the FPS table stopped at its share of the budget (${fps_s} s)"; elif [ "$rc" != 0 ]; then exit "$rc"; fi
if [ "$TRAIN" = 1 ]; then
    echo
    # shellcheck disable=SC2086
    timeout $(( BUDGET_S - fps_s )) python3 benchmarks/train_speed.py --device "$DEVICE" --configs $CONFIGS \
        --batch 8 --amp $AMP --grad-checkpoint off
    rc=$?
    if [ "$rc" = 124 ]; then echo "gpu.sh: the training table stopped at its share of the budget"; exit 0; fi
    exit "$rc"
fi
