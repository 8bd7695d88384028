#!/usr/bin/env bash
# Peer comparison on the same stamps (issue 23): megalut simulation-calibrated, megalut inside
# metacal, metacal on plain adaptive moments, and AnaCal (FPFS, analytic response).
# See README.md in this folder.
#
#   examples/metacal/peers/run.sh [WORKDIR]          # from the repository root, venv active
#
# Environment: J (worker processes, default 2); STAGES (default "psf simA simB A B diag scan summary",
# any subset); MODEL (default megalut_cli/data/fiducial.h5); MCAL_MODEL (for (2), see below).
# Outputs that exist are kept (delete them to redo a step). Every step's CPU time (user + sys,
# worker processes included) and wall time are appended to WORKDIR/times.txt by /usr/bin/time.
set -euo pipefail

W=${1:-/tmp/peers/work}
J=${J:-2}
STAGES=${STAGES:-"psf simA simB A B diag scan summary"}
MODEL=${MODEL:-megalut_cli/data/fiducial.h5}
# (2) runs the same networks on the metacal catalog: predict refuses a simulation-calibrated
# model there, and the shipped fiducial-metacal.h5 is fiducial.h5 relabelled (identical
# networks, shear_mode = "metacal"); without it, MODEL itself.
if [[ -z ${MCAL_MODEL:-} ]]; then
    MCAL_MODEL=$MODEL
    [[ -f megalut_cli/data/fiducial-metacal.h5 ]] && MCAL_MODEL=megalut_cli/data/fiducial-metacal.h5
fi
EX=examples/metacal/peers
mkdir -p "$W"

python -c 'import anacal' 2>/dev/null || { echo "run.sh: needs anacal in this environment (pip install anacal==0.8.3; not a megalut dependency)" >&2; exit 2; }

# One thread per process everywhere, so that CPU times compare and -j is the only parallelism.
export OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 NUMEXPR_NUM_THREADS=1 \
       NUMBA_NUM_THREADS=1 VECLIB_MAXIMUM_THREADS=1

# The metacal image engine: the FFT engine where it exists and imports, else the GalSim reference.
if python -c 'import megalut_cli.measure.metacal_fft' 2>/dev/null; then MCAL_ENGINE=fast; else MCAL_ENGINE=galsim; fi
echo "metacal engine: $MCAL_ENGINE" | tee "$W/engine.txt"

# step NAME OUTPUT CMD...: run CMD unless OUTPUT exists, logging "NAME user sys wall" to times.txt.
step() {
    local name=$1 out=$2; shift 2
    if [[ -e $out ]]; then echo "== $name: $out exists, kept"; return; fi
    echo "== $name: $*"
    /usr/bin/time -f "$name %U %S %e" -a -o "$W/times.txt" "$@"
}
has() { [[ " $STAGES " == *" $1 "* ]]; }

if has psf; then
    # The PSF image for --psf: megalut's convention (centred on the stamp's true centre).
    step psf "$W/psf.fits" python -c "import galsim, sys; galsim.Gaussian(sigma=2.0).drawImage(nx=64, ny=64, scale=1.0).write(sys.argv[1])" "$W/psf.fits"
fi

# measure_all SET: the four estimators on the stamps of $W/SET-stamps.fits (truth $W/SET.fits).
measure_all() {
    local s=$1
    step "measure:$s" "$W/$s-meas.fits" megalut measure "$W/$s-stamps.fits" "$W/$s.fits" -o "$W/$s-meas.fits" -j "$J" -q
    # (1) simulation-calibrated
    step "predict:$s" "$W/$s-sc.fits" megalut predict "$W/$s-meas.fits" --model "$MODEL" -o "$W/$s-sc.fits" -j 1 -q
    # (2) the same networks inside metacal
    step "measure-metacal:$s" "$W/$s-mcal.fits" megalut measure "$W/$s-stamps.fits" "$W/$s.fits" -o "$W/$s-mcal.fits" \
        --psf "$W/psf.fits" --metacal --engine "$MCAL_ENGINE" --seed 3 -j "$J" -q
    step "predict-metacal:$s" "$W/$s-mcal-nn.fits" megalut predict "$W/$s-mcal.fits" --model "$MCAL_MODEL" -o "$W/$s-mcal-nn.fits" -j 1 -q
    # (2') the same networks averaged over the stamp's rotations and reflections (issue 39)
    step "predict-metacal-d4:$s" "$W/$s-mcal-nn4.fits" megalut predict "$W/$s-mcal.fits" --model fiducial-metacal-d4 -o "$W/$s-mcal-nn4.fits" -j 1 -q
    # (3) metacal on plain adaptive moments
    step "adamom-metacal:$s" "$W/$s-mcal-am.fits" python "$EX/adamom_metacal.py" "$W/$s-mcal.fits" -o "$W/$s-mcal-am.fits"
    # (4) AnaCal at the adaptive-moment centroid of the plain measurement
    step "anacal:$s" "$W/$s-anacal.fits" python "$EX/anacal_shear.py" "$W/$s-stamps.fits" "$W/$s-meas.fits" \
        --psf "$W/psf.fits" -o "$W/$s-anacal.fits" --seed 5
}

if has simA; then
    # A: Sérsic galaxies, common random numbers: 4 shears x 5000 galaxy pairs (the same under every shear).
    step simulate:A "$W/A.fits" megalut simulate examples/fiducial/vo-crn.toml -o "$W/A.fits" --stamps "$W/A-stamps.fits" \
        --n-cases 4 --n-realizations 10000 --seed 7 -j "$J" -q
fi
if has simB; then
    # B: 30 real COSMOS galaxies and their Sérsic twins, 10 shears x 30 galaxies x a 90-degree pair,
    # identical shears, rotations, offsets, fluxes and noise seeds.
    step simulate:B-real "$W/B-real.fits" megalut simulate examples/realgal/fiducial.toml -o "$W/B-real.fits" \
        --stamps "$W/B-real-stamps.fits" --n-cases 10 --seed 14 -j "$J" -q
    step simulate:B-twin "$W/B-twin.fits" megalut simulate examples/realgal/fiducial.toml galaxy.twin=sersic \
        -o "$W/B-twin.fits" --stamps "$W/B-twin-stamps.fits" --n-cases 10 --seed 14 -j "$J" -q
fi

if has A; then
    measure_all A
    for e in sc mcal-nn mcal-nn4 mcal-am anacal; do
        step "evaluate:A-$e" "$W/A-$e.json" sh -c 'megalut evaluate "$1" --bootstrap 500 --json "$2" -q > "$3"' _ \
            "$W/A-$e.fits" "$W/A-$e.json" "$W/A-$e.txt"
    done
fi

if has B; then
    measure_all B-real
    measure_all B-twin
    for e in sc mcal-nn mcal-nn4 mcal-am anacal; do
        for t in real twin; do  # each set alone (the definitions of the single-set evaluation, for compare.py)
            step "evaluate:B-$t-$e" "$W/B-$t-$e.json" sh -c 'megalut evaluate "$1" --errors fit --json "$2" -q > "$3"' _ \
                "$W/B-$t-$e.fits" "$W/B-$t-$e.json" "$W/B-$t-$e.txt"
        done
        step "evaluate:B-$e" "$W/B-$e.json" sh -c 'megalut evaluate "$1" --twin "$2" --bootstrap 1000 --json "$3" -q > "$4"' _ \
            "$W/B-real-$e.fits" "$W/B-twin-$e.fits" "$W/B-$e.json" "$W/B-$e.txt"
    done
fi

if has diag; then
    # Diagnostics of AnaCal on set A (not part of the comparison; "truth" uses the simulation's
    # true centres): the same galaxies, shears and offsets without noise (AnaCal without its
    # noise image, c0 of the noisy set); on the noisy stamps: at the stamp centre, at the true
    # centre, without the noise image.
    step simulate:A0 "$W/A0.fits" megalut simulate examples/fiducial/vo-crn.toml noise.sigma=0.0 -o "$W/A0.fits" \
        --stamps "$W/A0-stamps.fits" --n-cases 4 --n-realizations 10000 --seed 7 -j "$J" -q
    step measure:A0 "$W/A0-meas.fits" megalut measure "$W/A0-stamps.fits" "$W/A0.fits" -o "$W/A0-meas.fits" -j "$J" -q
    # the c0 of the noisy set: its noise sigma (the median skymad of A)
    SIG=$(python -c 'import sys, fitsio; print(fitsio.read_header(sys.argv[1], 1)["ANNOISE"])' "$W/A-anacal.fits")
    step anacal:A0 "$W/A0-anacal.fits" python "$EX/anacal_shear.py" "$W/A0-stamps.fits" "$W/A0-meas.fits" \
        --psf "$W/psf.fits" -o "$W/A0-anacal.fits" --noise-sigma "$SIG" --no-noise-array
    step anacal:A-stampcentre "$W/A-anacal-stampcentre.fits" python "$EX/anacal_shear.py" "$W/A-stamps.fits" \
        "$W/A-meas.fits" --psf "$W/psf.fits" -o "$W/A-anacal-stampcentre.fits" --seed 5 --centre stamp
    step anacal:A-truecentre "$W/A-anacal-truecentre.fits" python "$EX/anacal_shear.py" "$W/A-stamps.fits" \
        "$W/A-meas.fits" --psf "$W/psf.fits" -o "$W/A-anacal-truecentre.fits" --seed 5 --centre truth
    step anacal:A-nonoiseimage "$W/A-anacal-nonoiseimage.fits" python "$EX/anacal_shear.py" "$W/A-stamps.fits" \
        "$W/A-meas.fits" --psf "$W/psf.fits" -o "$W/A-anacal-nonoiseimage.fits" --no-noise-array
    for e in A0-anacal A-anacal-stampcentre A-anacal-truecentre A-anacal-nonoiseimage; do
        step "evaluate:$e" "$W/$e.json" sh -c 'megalut evaluate "$1" --bootstrap 500 --json "$2" -q > "$3"' _ \
            "$W/$e.fits" "$W/$e.json" "$W/$e.txt"
    done
fi

if has scan; then
    # How AnaCal's kernel and c0 change its noise (chosen on this, not on any bias; README.md).
    python "$EX/scan_settings.py" "$W" | tee "$W/scan.md"
fi

if has summary; then
    python "$EX/summarize.py" "$W" | tee "$W/summary.md"
    python "$EX/compare.py" "$W" | tee "$W/compare.md"
fi
