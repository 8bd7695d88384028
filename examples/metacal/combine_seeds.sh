#!/usr/bin/env bash
# Combine runs of run_realgal.sh made with other seeds (more rings per galaxy, the same four
# shears) and evaluate them as one experiment. From the repository root:
#
#   examples/metacal/combine_seeds.sh EXPERIMENT N_CASES SEED SEED ...
#
# reads /tmp/mcx/EXPERIMENT-sSEED-nN_CASES/{real,twin}-{a,b,c}.fits and writes the combined
# catalogs and evaluations to $W (default /tmp/mcx/EXPERIMENT-s<SEED+SEED+...>-nN_CASES).
set -euo pipefail
EXP=${1:?usage: combine_seeds.sh EXPERIMENT N_CASES SEED SEED ...}
NC=${2:?}
shift 2
SEEDS=("$@")
EX=examples/metacal
T="python $EX/mcal_tools.py"
BOOT=${BOOT:-1000}
W=${W:-/tmp/mcx/$EXP-s$(IFS=+; echo "${SEEDS[*]}")-n$NC}
mkdir -p "$W"
for e in ${LETTERS:-a b c}; do
  for set in real twin; do
    $T concat "$W/$set-$e.fits" $(for s in "${SEEDS[@]}"; do echo "/tmp/mcx/$EXP-s$s-n$NC/$set-$e.fits"; done)
  done
done
examples/metacal/evaluate_all.sh "$W" $([[ $EXP == e1-* ]] && echo 30)
