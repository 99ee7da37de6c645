#!/usr/bin/env bash
# Issue 22's target runs (docs/grasping.md, "Where issue 22's targets stand"): the deployed
# configuration (re-aligned on static anchors, robust grasps) on the three opaque shared sets,
# SSRA + GSSA + LWLR, 3 sampling seeds, simulator seeds 0, 1 and 2, both grippers; then the table
# of benches/grasp/targets.py. SIMULATED predictions, PROXY scores.
#
#   bash benches/grasp/targets.sh OUT                                  # the simulator's defaults
#   bash benches/grasp/targets.sh OUT --off noise                      # one component off
#   bash benches/grasp/targets.sh OUT --sim-config sim.json            # other strengths
#
# Flags after OUT go to every `moma grasp-eval` call. MOMA (default target/release/moma, built by
# `cargo build --release -p moma-cli`), SHARED (default ../shared) and METHODS (default
# ssra,gssa,lwlr) may be set. About 3 min on the 2-core build machine.
set -euo pipefail

if [[ $# -lt 1 || $1 == -h || $1 == --help ]]; then
    sed -n '2,13p' "$0" | sed 's/^# \{0,1\}//'
    exit 2
fi
out=$1
shift
here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/../.." && pwd)
moma=${MOMA:-$root/target/release/moma}
shared=${SHARED:-$root/../shared}
if [[ ! -x $moma ]]; then
    echo "targets.sh: $moma is not an executable; run \`cargo build --release -p moma-cli\` or set MOMA" >&2
    exit 2
fi
sets=()
for s in gqcnn-primesense graspnet6dof-table m2t2-table; do
    if [[ ! -d $shared/data/$s ]]; then
        echo "targets.sh: $shared/data/$s is missing; set SHARED to the shared folder" >&2
        exit 2
    fi
    sets+=(--set "$shared/data/$s")
done

for gripper in suction parallel; do
    mkdir -p "$out/$gripper"
    for seed in 0 1 2; do
        # the JSON goes to a temporary name first: a half-written file never looks like a run
        "$moma" grasp-eval "${sets[@]}" --simulate --sim-seed "$seed" --methods "${METHODS:-ssra,gssa,lwlr}" \
            --seeds 3 --realign anchors --gripper "$gripper" --json -o "$out/$gripper/out$seed" "$@" \
            > "$out/$gripper/s$seed.json.tmp" 2> "$out/$gripper/log$seed.txt"
        mv "$out/$gripper/s$seed.json.tmp" "$out/$gripper/s$seed.json"
    done
done
python3 "$here/targets.py" "$out"
