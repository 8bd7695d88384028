#!/usr/bin/env bash
# One device session's checks (benchmarks/gpu.md), run in the repository root of a GPU
# machine that has Python, JAX with CUDA, numba, numpy, scipy and h5py but not GalSim,
# astropy or fitsio: those come in a folder of unpacked wheels named by SITE (default .site),
# built here by benchmarks/gpu_site.sh and carried (device tool: carry [".site"]).
# Stages, most important first, each under its own time limit; logs go to OUT (default .):
#   1. benchmarks/bench_gpu.py at the documented size (stamps/s and rows/s, device vs 1 core)
#   2. tests/test_gpu.py, slow tests included, on the GPU
#   3. benchmarks/profile_gpu.py: where a unit's time goes, for two batch and noise sizes
#   4. `megalut simulate --measure` end to end: --device gpu (twice: the second run finds the
#      compiled kernels in the cache) against --device cpu -j 0 (all cores)
# STAGES (default "bench tests profile cli") picks stages.
set -u
STAGES=" ${STAGES:-bench tests profile cli} "
SITE=${SITE:-.site}
OUT=${OUT:-.}
export PYTHONPATH="$PWD/$SITE:$PWD" PYTHONUNBUFFERED=1 NUMBA_CACHE_DIR=/tmp/numba-cache
export MPLBACKEND=Agg
PY=${PYTHON:-python3}
t0=$(date +%s)
stamp() { echo "== $(($(date +%s) - t0)) s: $*"; }

stamp setup
nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.max.sm --format=csv
lscpu | grep -E "Model name|^CPU\(s\)"
$PY -m pip install -q --no-deps --no-build-isolation --no-index -e . >/dev/null 2>&1 \
    || echo "(pip install -e . failed: running from PYTHONPATH)"
$PY - <<'EOF' || exit 1
import galsim, astropy, fitsio, numba, numpy, scipy, h5py, jax
print("python", __import__("sys").version.split()[0], "jax", jax.__version__, "numpy",
      numpy.__version__, "numba", numba.__version__, "galsim", galsim.__version__,
      "astropy", astropy.__version__)
print("jax devices:", jax.devices())
import megalut_cli.gpu as g
print("device_problem:", g.device_problem())
EOF

if [[ $STAGES == *" bench "* ]]; then
stamp "bench_gpu.py"
timeout "${BENCH_S:-300}" $PY benchmarks/bench_gpu.py --cases 40 --realizations 2000 \
    --rows 10000000 --repeats "${REPEATS:-3}" 2>&1 | tee "$OUT/bench_gpu.log"
echo "bench rc ${PIPESTATUS[0]}"
fi

if [[ $STAGES == *" tests "* ]]; then
stamp "tests/test_gpu.py (slow included)"
timeout "${TESTS_S:-150}" $PY -m pytest tests/test_gpu.py -m "slow or not slow" -q \
    -p no:cacheprovider -rs 2>&1 | tail -25 | tee "$OUT/test_gpu.log"
fi

if [[ $STAGES == *" profile "* ]]; then
stamp "profile_gpu.py"
timeout "${PROFILE_S:-200}" $PY benchmarks/profile_gpu.py --cases 40 --realizations 2000 \
    --batch 4096 32768 --noise 32768 131072 --repeats 1 2>&1 | tee "$OUT/profile_gpu.log"
fi

if [[ $STAGES == *" cli "* ]]; then
stamp "megalut simulate --measure end to end"
N_CASES=${N_CASES:-200}
N_REA=${N_REA:-2000}
# MIN_COMPILE_S: JAX keeps kernels that took this long to compile (megalut's default 0.5 s)
[[ -n ${MIN_COMPILE_S:-} ]] && export JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=$MIN_COMPILE_S
for dev in gpu gpu cpu; do
    s=$(date +%s.%N)
    timeout "${SIM_S:-120}" $PY -m megalut_cli simulate examples/fiducial/tp.toml \
        -o "/tmp/sim-$dev.fits" --measure --n-cases "$N_CASES" --n-realizations "$N_REA" \
        --device "$dev" -j 0 -q --overwrite
    rc=$?
    e=$(date +%s.%N)
    echo "simulate --device $dev -j 0: rc $rc, $(awk "BEGIN{print $e - $s}") s" | tee -a "$OUT/simulate.log"
done
$PY - <<'EOF' 2>&1 | tee -a "$OUT/simulate.log"
import numpy as np
from astropy.table import Table
g, c = Table.read("/tmp/sim-gpu.fits", hdu=1), Table.read("/tmp/sim-cpu.fits", hdu=1)
d = np.flatnonzero(np.asarray(g["flags"]) != np.asarray(c["flags"]))
bits = sorted(set(np.bitwise_xor(np.asarray(g["flags"])[d], np.asarray(c["flags"])[d]).tolist()))
print(len(g), "rows; flags differ on", len(d), "stamps, bits", bits)
for k in ("adamom_flux", "adamom_g1", "adamom_g2", "adamom_sigma", "adamom_rho4", "snr"):
    ok = np.isfinite(g[k]) & np.isfinite(c[k])
    print(f"  max |{k} gpu - cpu| = {np.max(np.abs(g[k][ok] - c[k][ok])):.2e}")
EOF
fi
stamp done
