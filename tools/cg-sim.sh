# Sourced by the callgrind scripts (tools/callgrind-compare.sh, tools/callgrind-listing.sh,
# tools/callgrind-embree-listing.sh): callgrind's simulator options, in one place.
#
# cg_cache: the cache model, by default this project's first build machine's as the chained-load
# measurement saw it (`examples/memlat.rs`: 32 KiB L1D, a 1 MiB last level, the private L2);
# CG_D1 and CG_LL override it, e.g. `CG_D1=49152,12,64 CG_LL=2097152,16,64` for the 48 KiB L1D
# and 2 MiB L2 of the Xeon of session 45.
cg_cache=(--I1=32768,8,64 --D1="${CG_D1:-32768,8,64}" --LL="${CG_LL:-1048576,8,64}")

# cg_event_options EVENT: sets `cg_options` to what counting EVENT needs: nothing for
# instructions (Ir), the branch simulator for branch events (Bc, Bcm, Bi, Bim), the cache model
# for the others (DLmr, D1mr, Dr...).
cg_event_options() {
    case $1 in
        Ir) cg_options=() ;;
        B*) cg_options=(--branch-sim=yes) ;;
        *) cg_options=(--cache-sim=yes "${cg_cache[@]}") ;;
    esac
}
