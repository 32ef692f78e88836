#!/usr/bin/env bash
# Run every perfcap benchmark in sequence. Usage: benchmarks/run_all.sh [PYTHON]
# Each script prints PASS/FAIL per target and exits 0; this script fails only if one crashes.
set -euo pipefail
cd "$(dirname "$0")/.."
PY="${1:-.venv/bin/python}"
for b in bench_bus bench_clocksync bench_phone_clock bench_replay bench_recorder bench_serial bench_serial_codecs bench_fusion bench_hid bench_serve bench_cycles bench_puppet; do
    echo
    echo "################ benchmarks/$b.py"
    "$PY" "benchmarks/$b.py"
done
