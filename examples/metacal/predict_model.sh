#!/usr/bin/env bash
# Another metacal model on the stamps of run_realgal.sh runs (README.md, estimator d): from the
# repository root,
#
#   examples/metacal/predict_model.sh MODEL.h5 LETTER DIR [DIR ...]
#
# predicts each DIR's merged metacal catalogs {real,twin}.fits with MODEL into
# {real,twin}-LETTER.fits (same stamps, same rings, same fixnoise as a, b, c). Evaluate with
# LETTERS="a b c LETTER" evaluate_all.sh DIR (one seed) or combine_seeds.sh (several).
set -euo pipefail
MODEL=${1:?usage: predict_model.sh MODEL.h5 LETTER DIR [DIR ...]}
E=${2:?}
shift 2
for W in "$@"; do
  for set in real twin; do
    megalut predict "$W/$set.fits" --model "$MODEL" -o "$W/$set-$E.fits" -j "${J:-2}" --overwrite -q
  done
done
