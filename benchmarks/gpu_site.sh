#!/usr/bin/env bash
# Build the folder of unpacked wheels that benchmarks/gpu_session.sh needs on a GPU machine
# whose Python (3.12 on the lent H200) lacks GalSim, astropy and fitsio. Run here, in the
# repository root; the folder (default .site, git-ignored through .git/info/exclude) must
# stay under the device tool's 64 MiB with the working tree: the wheels' debug symbols,
# tests and GalSim's sensor and Roman data are dropped, and astropy's IERS tables.
set -eu
SITE=${SITE:-.site}
PYVER=${PYVER:-3.12}
EXCLUDE=$(git rev-parse --git-path info/exclude)
mkdir -p "$(dirname "$EXCLUDE")"
for d in "/$SITE/" "/.whl/"; do grep -qx "$d" "$EXCLUDE" 2>/dev/null || echo "$d" >> "$EXCLUDE"; done
python3 -m pip download -q --no-deps --only-binary=:all: --python-version "$PYVER" \
    --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 \
    --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -d .whl \
    "galsim==$(python3 -c 'import galsim; print(galsim.__version__)')" LSSTDESC.Coord \
    astropy astropy-iers-data pyerfa fitsio
rm -rf "$SITE" && mkdir -p "$SITE"
for w in .whl/*.whl; do unzip -q -o "$w" -d "$SITE"; done
strip --strip-debug "$SITE"/galsim/_galsim*.so "$SITE"/galsim.libs/*.so*
rm -rf "$SITE"/galsim/share/sensors "$SITE"/galsim/share/roman "$SITE"/galsim/include
find "$SITE" -mindepth 3 -type d -name tests -prune -exec rm -rf {} +  # not astropy/tests
find "$SITE" \( -name "*.pyx" -o -name "*.c" -o -name RECORD \) -delete
rm -rf "$SITE"/astropy_iers_data/data/*
du -sh "$SITE"
