# Sourced by the bench drivers that run long measurements from a fixed commit:
#   source bench/snapshot.sh; snap=$(snapshot REPO COMMIT)
# exports COMMIT of the checkout REPO with `git archive` to /tmp/asac_bench_<COMMIT> (once; a finished
# export is reused) and prints that folder, so that edits in the working tree never reach a run going on.
snapshot() {
    local repo=$1 commit=$2
    local snap=/tmp/asac_bench_$commit
    if [ ! -d "$snap" ]; then
        rm -rf "$snap.tmp" && mkdir -p "$snap.tmp"
        git -C "$repo" archive "$commit" | tar -x -C "$snap.tmp"
        mv "$snap.tmp" "$snap"
    fi
    echo "$snap"
}
