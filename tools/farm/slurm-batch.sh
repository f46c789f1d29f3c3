#!/usr/bin/env bash
# Slurm array job: each array task renders its own shard of the frames with `vscatter batch`.
#
#   sbatch --array=1-N tools/farm/slurm-batch.sh 'INPUT_PATTERN' OUT_DIR [extra vscatter batch flags...]
#
# Task i of N runs: vscatter batch INPUT_PATTERN --out-dir OUT_DIR --shard i/N [flags...]
# Number the array from 1 (--array=1-N): the shard index is the array task id, and shards count from 1.
# Quote INPUT_PATTERN so the submitting shell does not expand its globs / #### itself.
# The binary is $VSCATTER if set (sbatch passes the submitting environment on), else `vscatter` on PATH.
# Relative paths are taken from the directory you ran sbatch in (Slurm's default working directory).
#
#SBATCH --job-name=vscatter-batch
#SBATCH --ntasks=1
#SBATCH --cpus-per-task=2
#SBATCH --output=vscatter-batch.%A_%a.log
# (%A = array job id, %a = array task id: one log per task, written in the submit directory.)
set -euo pipefail

# Name spelled out: inside a job $0 is Slurm's spooled copy (.../slurm_script), not this path.
usage() {
  echo "usage: sbatch --array=1-N tools/farm/slurm-batch.sh 'INPUT_PATTERN' OUT_DIR [extra vscatter batch flags...]" >&2
  echo "  runs 'vscatter batch INPUT_PATTERN --out-dir OUT_DIR --shard TASK_ID/N [flags...]' per array task" >&2
  echo "  (binary: \$VSCATTER, else vscatter on PATH)" >&2
  exit 2
}
[ $# -ge 2 ] && [ -n "$1" ] && [ -n "$2" ] || usage
INPUT=$1 OUT=$2
shift 2

# Only meaningful as an array task: the shard comes from the array index.
if [ -z "${SLURM_ARRAY_TASK_ID:-}" ]; then
  echo "slurm-batch.sh: SLURM_ARRAY_TASK_ID is not set; submit with: sbatch --array=1-N ..." >&2
  exit 2
fi
# SLURM_ARRAY_TASK_COUNT is only set by newer Slurm; older ones give just MIN/MAX.
# MAX-MIN+1 equals the count for a contiguous --array=1-N, the form this script expects.
COUNT=${SLURM_ARRAY_TASK_COUNT:-$(( SLURM_ARRAY_TASK_MAX - SLURM_ARRAY_TASK_MIN + 1 ))}

VSCATTER=${VSCATTER:-vscatter}
mkdir -p "$OUT"
echo "$(date -Is) $(hostname) task $SLURM_ARRAY_TASK_ID/$COUNT (job ${SLURM_ARRAY_JOB_ID:-?}): $VSCATTER batch $INPUT --out-dir $OUT --shard $SLURM_ARRAY_TASK_ID/$COUNT $*"
exec "$VSCATTER" batch "$INPUT" --out-dir "$OUT" --shard "$SLURM_ARRAY_TASK_ID/$COUNT" "$@"
