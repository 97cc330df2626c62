# Sourced by the evaluation scripts of a held-out scene family (eval-thin.sh, eval-subpixel.sh):
#   family_logs SCENE PREFIX COUNT RESOLUTION [RIG]
# records captures of SCENE (RIG: five-view by default, or line5, grid3x3 …) with seeds
# 1..COUNT over the working range each log
# carries, into PREFIX-<seed>.mcap (kept when already there), and leaves their paths in the
# array `logs`. Run from the repository root after building `record`.
family_logs() {
    local scene=$1 prefix=$2 count=$3 resolution=$4 rig=${5:-five-view} seed log
    logs=()
    mkdir -p "$(dirname "$prefix")"
    for seed in $(seq 1 "$count"); do
        log="$prefix-$seed.mcap"
        [ -f "$log" ] || target/release/record --scene "$scene" --seed "$seed" --rig "$rig" \
            --resolution "$resolution" --log-working-range -o "$log" -q --no-blueprint
        logs+=("$log")
    done
}
