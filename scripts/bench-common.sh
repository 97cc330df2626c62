# Sourced by the benchmark scripts: builds the release binaries, sets R (the replay binary) and T
# (a scratch folder removed on exit), and prints the host the figures come from.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
cargo build --release -q -p record -p replay
R=target/release/replay
T=$(mktemp -d)
trap 'rm -rf "$T"' EXIT
echo "host: $(lscpu | sed -n 's/^Model name: *//p') ($(nproc) vCPUs)"
