#!/usr/bin/env bash
# All evaluations of one experiment directory of run_realgal.sh / combine_seeds.sh (from the
# repository root): examples/metacal/evaluate_all.sh DIR [30]
# DIR holds {real,twin}-{a,b,c}.fits (LETTERS="a b c d": also d, networks trained in metacal
# mode, predict_model.sh); with "30", also on the 30 galaxies of
# ../realgal/fiducial.toml. Writes paired-*.{txt,json} (megalut evaluate --twin),
# {real,twin}-*.{txt,json} (each set alone, bootstrap over rings), rsel-a*.json (mcal_tools.py
# paired: the weighted metacal scheme with the weights' selection response) and table.md.
set -euo pipefail
W=${1:?usage: evaluate_all.sh DIR [30]}
SUB=${2:-}
T="python examples/metacal/mcal_tools.py"
BOOT=${BOOT:-1000}
for e in ${LETTERS:-a b c}; do
  megalut evaluate "$W/real-$e.fits" --twin "$W/twin-$e.fits" --bootstrap "$BOOT" --seed 1 \
    --json "$W/paired-$e.json" --overwrite > "$W/paired-$e.txt"
  for set in real twin; do
    megalut evaluate "$W/$set-$e.fits" --errors bootstrap --bootstrap "$BOOT" --seed 1 \
      --json "$W/$set-$e.json" --overwrite > "$W/$set-$e.txt"
  done
  if [[ $SUB == 30 ]]; then
    for set in real twin; do $T subset "$W/$set-$e-30.fits" "$W/$set-$e.fits" examples/realgal/fiducial.toml; done
    megalut evaluate "$W/real-$e-30.fits" --twin "$W/twin-$e-30.fits" --bootstrap "$BOOT" --seed 1 \
      --json "$W/paired-$e-30.json" --overwrite > "$W/paired-$e-30.txt"
  fi
done
for e in ${LETTERS:-a b c}; do
  [[ $e == b || $e == c ]] && continue  # the networks in metacal mode: weights with R_sel
  $T paired "$W/rsel-$e.json" "$W/real-$e.fits" "$W/twin-$e.fits" "$BOOT" 1
  if [[ $SUB == 30 ]]; then $T paired "$W/rsel-$e-30.json" "$W/real-$e-30.fits" "$W/twin-$e-30.fits" "$BOOT" 1; fi
done
$T table "$W"/paired-*.json "$W"/rsel-*.json | tee "$W/table.md"
