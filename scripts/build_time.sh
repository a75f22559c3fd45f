#!/usr/bin/env bash
# Compile time of each C++ plugin shim, alone and with the flags build.rs uses (one core),
# written to docs/bench/build_time.txt (README quotes that file). Run after scripts/setup.sh.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
SP=$(.venv/bin/python -c "import sysconfig; print(sysconfig.get_paths()['purelib'])")
BRIDGE=$(ls -d target/release/build/fluo-mitsuba-*/out/cxxbridge | head -1)
out=docs/bench/build_time.txt
{
    echo "# seconds to compile each shim alone (g++ -O3, build.rs flags, one core; $(nproc) cores, $(date -u +%F))"
    for f in mitsuba/plugins/*.cpp; do
        start=$(date +%s.%N)
        c++ -O3 -std=c++17 -fPIC -msse4.2 -fno-strict-aliasing -fvisibility=hidden -fvisibility-inlines-hidden \
            -fno-math-errno -w -I mitsuba/include/fluo -I "$BRIDGE/include" -I "$BRIDGE/crate" \
            -I "$SP/mitsuba/include" -I "$SP/drjit/include" -I "$SP/nanobind/include" \
            -I "$SP/nanobind/ext/robin_map/include" -c "$f" -o /tmp/fluo_build_time.o
        printf '%-36s %6.1f\n' "$(basename "$f")" "$(echo "$(date +%s.%N) - $start" | bc)"
    done
} > "$out"
cat "$out"
