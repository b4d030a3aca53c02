#!/bin/bash
# Submit the worker array and, after it (whatever became of its tasks), the gather job. The
# jobs inherit STUDY, OUT, TRIALS, CLAIM_TIMEOUT and JSPHERE_VENV (the environment jsphere is
# installed in, with the GPU extra: pip install -e ".[gpu]"; see worker_array.sbatch) from this shell.
#
#   STUDY=study.toml OUT=/shared/$USER/study TRIALS=10000000 examples/cluster/submit_array.sh
set -euo pipefail

here=$(dirname "$0")
array=$(sbatch --parsable "$here/worker_array.sbatch")
array=${array%%;*}  # "jobid;cluster" on federated clusters
gather=$(sbatch --parsable --dependency="afterany:$array" "$here/gather.sbatch")
echo "workers: job $array; gather: job ${gather%%;*} (when the workers have ended)"
