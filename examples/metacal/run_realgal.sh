#!/usr/bin/env bash
# Metacal real-vs-twin experiments of issue 23 (README.md). From the repository root:
#
#   examples/metacal/run_realgal.sh EXPERIMENT [N_CASES] [SEED]
#
# EXPERIMENT: e1-symmetrized | e1-footprint (100 galaxies, N_CASES = 100 x rings per galaxy,
# default 100), e2-noise (30 galaxies, N_CASES = 30 x rings per galaxy, default 300) or
# e2-noise-100 (all 100 galaxies, N_CASES = 100 x rings per galaxy, default 1000).
# Outputs under $W (default /tmp/mcx/EXPERIMENT-sSEED-nN_CASES); -j $J (default 2); the
# engine $ENGINE (default galsim; "fast" measures and metacal-measures with the fast engine,
# the real galaxies are drawn by GalSim either way); the sets $SETS (default "real twin";
# "real" alone skips the twins and the paired evaluations); $EXTRA: more KEY=VALUE overrides
# of the config for every simulate run (e.g. EXTRA="galaxy.hst_noise=whiten").
# For each set (real galaxies, Sersic twins) and each shear (g1, g2) in {+0.02, -0.02}^2 one
# simulate run with the same seed (common random numbers), merged into one catalog of 4
# cases, then three estimators on the same stamps:
#   a  the shipped networks in metacal mode (megalut_cli/data/fiducial-metacal.h5: the
#      networks of fiducial.h5 on the noshear features, calibrated by their response)
#   b  metacal on plain adaptive moments (pre_g := adamom_g of each version, no networks)
#   c  the shipped simulation-calibrated model (fiducial.h5) on the plain features
# and a paired real-vs-twin evaluation of each (bootstrap over galaxies; evaluate_all.sh);
# with e1-*, also on the 30 galaxies of ../realgal/fiducial.toml. More rings: run again with
# other seeds and combine_seeds.sh.
set -euo pipefail
EXP=${1:?usage: run_realgal.sh e1-symmetrized|e1-footprint|e2-noise|e2-noise-100 [N_CASES] [SEED]}
case $EXP in
  e1-*) NC=${2:-100} ;;
  e2-noise-100) NC=${2:-1000} ;;
  e2-*) NC=${2:-300} ;;
  *) echo "unknown experiment $EXP" >&2; exit 2 ;;
esac
SEED=${3:-1}
EX=examples/metacal
CFG=$EX/$EXP.toml
T="python $EX/mcal_tools.py"
J=${J:-2}
ENGINE=${ENGINE:-galsim}
SETS=${SETS:-real twin}
W=${W:-/tmp/mcx/$EXP-s$SEED-n$NC}
mkdir -p "$W"
LOG=$W/times.log
timed() {  # timed LABEL COMMAND...: wall and CPU (user+sys, children included) into $LOG
  local label=$1; shift
  /usr/bin/time -f "$label: %e s wall, %U s user + %S s sys" -a -o "$LOG" "$@"
}

SHEARS=("0.02 0.02" "0.02 -0.02" "-0.02 0.02" "-0.02 -0.02")
for set in $SETS; do
  twin=none; [ $set = twin ] && twin=sersic
  for k in 0 1 2 3; do
    read -r g1 g2 <<<"${SHEARS[$k]}"
    # shellcheck disable=SC2086  # EXTRA: words, one override each
    timed "simulate $set shear $k" megalut simulate "$CFG" shear.g1=$g1 shear.g2=$g2 galaxy.twin=$twin ${EXTRA:-} \
      -o "$W/$set-s$k.fits" --n-cases "$NC" --seed "$SEED" --measure --metacal --engine "$ENGINE" -j "$J" --overwrite -q
  done
  $T merge "$W/$set.fits" "$W/$set-s0.fits" "$W/$set-s1.fits" "$W/$set-s2.fits" "$W/$set-s3.fits"
  # (a) the shipped networks in metacal mode
  timed "predict $set a" megalut predict "$W/$set.fits" --model megalut_cli/data/fiducial-metacal.h5 \
    -o "$W/$set-a.fits" -j "$J" --overwrite -q
  # (b) metacal on adaptive moments
  $T adamom "$W/$set-b.fits" "$W/$set.fits"
  # (c) simulation-calibrated: the plain features of the same stamps
  $T plain "$W/$set-plain.fits" "$W/$set.fits"
  timed "predict $set c" megalut predict "$W/$set-plain.fits" --model megalut_cli/data/fiducial.h5 \
    -o "$W/$set-c.fits" -j "$J" --overwrite -q
done

# paired real-vs-twin evaluations of (a), (b), (c) (and each set alone), table.md
if [[ $SETS == "real twin" ]]; then
  examples/metacal/evaluate_all.sh "$W" $([[ $EXP == e1-* ]] && echo 30)
fi
cat "$LOG"
