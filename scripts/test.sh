#!/usr/bin/env bash
# The README's test command: installs what the tests need when it is missing, then runs the
# format check, clippy (warnings are errors) and every test of the workspace.
#
#   scripts/test.sh              everything (what CI runs through .ci/run)
#   scripts/test.sh -- ARGS      passes ARGS to `cargo test --workspace` (e.g. `-- five_views`)
#
# Set-up it does (each step skipped when already done):
#   - Debian's mesa-vulkan-drivers: software Vulkan for the headless Rerun viewer screenshots
#     (apt-get as root, or through `sudo -n`); without it the two viewer tests fail with
#     "Failed to get render context", so a missing package stops the script here with that reason;
#   - ./.venv with the Python reference clients (mcap, safetensors, numpy, rerun-sdk) from
#     tests/python/requirements.txt;
#   - tests/js/node_modules with Foxglove's MCAP reader (@mcap/core), when npm is installed.
set -euo pipefail
cd "$(dirname "$0")/.."

# A clean build of the workspace's tests takes about 7 GB here; say what there is, so that a
# failure for lack of room reads as one.
echo "== disk: $(df -h . | awk 'NR == 2 { print $4 " free of " $2 }')"

echo "== software Vulkan for the headless Rerun viewer (Debian's mesa-vulkan-drivers)"
if command -v dpkg >/dev/null 2>&1 && ! dpkg -s mesa-vulkan-drivers >/dev/null 2>&1; then
    if [ "$(id -u)" = 0 ]; then
        as_root=()
    elif command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
        as_root=(sudo -n)
    else
        echo "mesa-vulkan-drivers is missing and cannot be installed here (not root, no password-less sudo):" >&2
        echo "  run 'sudo apt-get install mesa-vulkan-drivers' once, then this script again" >&2
        exit 1
    fi
    "${as_root[@]}" apt-get update -qq
    DEBIAN_FRONTEND=noninteractive "${as_root[@]}" apt-get install -y -qq mesa-vulkan-drivers >/dev/null
elif ! command -v dpkg >/dev/null 2>&1; then
    echo "not a Debian system: make sure a Vulkan driver (e.g. Mesa's lavapipe) is installed for the viewer tests" >&2
fi

echo "== Python reference clients in ./.venv"
if [ ! -x .venv/bin/python ]; then
    python3 -m venv .venv
fi
.venv/bin/python -m pip install --quiet --disable-pip-version-check -r tests/python/requirements.txt

echo "== Foxglove's MCAP reader (@mcap/core) in tests/js/node_modules"
if command -v npm >/dev/null 2>&1; then
    if [ ! -d tests/js/node_modules/@mcap/core ]; then
        npm ci --prefix tests/js --silent --no-audit --no-fund
    fi
else
    echo "npm is not installed: the tests that read logs with Foxglove's reader say so and skip it" >&2
fi

echo "== toolchain"
cargo --version
rustc --version

echo "== cargo fmt --all --check"
cargo fmt --all --check

echo "== cargo clippy --workspace --all-targets -- -D warnings"
cargo clippy --workspace --all-targets -- -D warnings

echo "== cargo test --workspace"
if [ "${1:-}" = "--" ]; then
    shift
fi
cargo test --workspace "$@"
