# Sourced by tools/ab-wall.sh and tools/ab-build.sh: the alternating runs both of them time.
#
# ab_runs DIR ROUNDS "SCENE..." BENCH-OPTION...
#
# For each round, each scene and each binary of the array `bins` in its order, one
# `${PIN:-} BIN bench SCENE BENCH-OPTION... --json DIR/K.I.SCENE.json ${EXTRA:-}` (K the binary's
# index, I the round); on a failure, prints the run's last log lines and exits.
ab_runs() {
    local d=$1 rounds=$2 scenes=$3 i s k
    shift 3
    [ "${#bins[@]}" -ge 2 ] || { echo "need a baseline and at least one other binary" >&2; exit 2; }
    for i in $(seq 1 "$rounds"); do
        for s in $scenes; do
            for k in "${!bins[@]}"; do
                # shellcheck disable=SC2086 # PIN is a command prefix, EXTRA a list of options
                if ! ${PIN:-} "${bins[$k]}" bench "$s" "$@" \
                    --json "$d/$k.$i.$(basename "$s").json" ${EXTRA:-} >"$d/log" 2>&1; then
                    echo "round $i: ${bins[$k]} bench $s failed:" >&2
                    tail -5 "$d/log" >&2
                    exit 1
                fi
            done
        done
    done
}
