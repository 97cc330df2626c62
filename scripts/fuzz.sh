#!/usr/bin/env bash
# A longer fuzzing campaign than the test command's: the fuzz targets of tests/e2e/fuzz.rs (the
# log reader with foreign set assembly, the ground-truth readers, the dataset description, the
# method configs, the weights loader) with FUZZ_CASES mutated inputs each (default 200000).
# A finding prints proptest's smallest failing mutation list; FUZZ_TRAP_BYTES=1 adds a backtrace
# of every allocation over 1 GiB.
# Usage: scripts/fuzz.sh [CASES]
set -euo pipefail
cd "$(dirname "$0")/.."
export FUZZ_CASES=${1:-200000}
time cargo test -p multiscopic-tests --test e2e -- fuzz --nocapture --test-threads 2
