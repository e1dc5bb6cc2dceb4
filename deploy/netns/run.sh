#!/usr/bin/env bash
# RSU, link emulator and OBU on three "hosts": Linux network namespaces joined by veth pairs.
#
#   v2i-rsu  10.10.1.1 <--veth--> 10.10.1.2  v2i-link  10.10.2.1 <--veth--> 10.10.2.2  v2i-obu
#   RSU listens on tcp/10.10.1.1:7447           OBU listens on tcp/10.10.2.2:7448
#                     the link emulator connects to both; no routing, no forwarding
#
# The link emulator is the only path between RSU and OBU (the RSU namespace has no route to
# 10.10.2.0/24), and loopback stays down in the RSU and link namespaces, so no service can lean
# on 127.0.0.1. It then watches the OBU's fused output from inside the OBU namespace (a local
# consumer on the vehicle "host"; only there is lo up, because traffic to a namespace's own
# address goes through its lo) until lists holding RSU objects arrive, and stops everything. Needs root and iproute2; re-running is safe (leftovers
# of an earlier run are removed first, and everything is removed on exit, Ctrl-C included).
#
#   sudo deploy/netns/run.sh                      # python3 on PATH must have v2i installed
#   sudo PYTHON=.venv/bin/python PROFILE=dsrc deploy/netns/run.sh
set -euo pipefail

PREFIX=${PREFIX:-v2i}
PYTHON=${PYTHON:-python3}
SCENARIO=${SCENARIO:-red-light-runner}
PROFILE=${PROFILE:-lte-v2x}
SEED=${SEED:-0}
DURATION_S=${DURATION_S:-30}      # scenario seconds the services run
STARTUP_S=${STARTUP_S:-5}         # scenario time zero this far ahead: every service must be up by then
MIN_RSU_LISTS=${MIN_RSU_LISTS:-20}  # fused lists with RSU objects to see before declaring success

RSU_NS=$PREFIX-rsu LINK_NS=$PREFIX-link OBU_NS=$PREFIX-obu
RSU_IF=$PREFIX-r0 LINK_RSU_IF=$PREFIX-l0 LINK_OBU_IF=$PREFIX-l1 OBU_IF=$PREFIX-o0
RSU_ADDR=10.10.1.1 LINK_RSU_ADDR=10.10.1.2 LINK_OBU_ADDR=10.10.2.1 OBU_ADDR=10.10.2.2
RSU_EP=tcp/$RSU_ADDR:7447 OBU_EP=tcp/$OBU_ADDR:7448

# Resolve before entering the namespaces: `ip netns exec` must run the very same interpreter.
PYTHON=$(command -v "$PYTHON")
PYTHON=$(readlink -f "$(dirname "$PYTHON")")/$(basename "$PYTHON")
HERE=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
LOG_DIR=$(mktemp -d "${TMPDIR:-/tmp}/v2i-netns.XXXXXX")
PIDS=()

remove_namespaces() {
    local name
    for name in "$RSU_NS" "$LINK_NS" "$OBU_NS"; do
        ip netns del "$name" 2>/dev/null || true  # takes the veth ends inside with it
    done
    for name in "$RSU_IF" "$OBU_IF"; do
        ip link del "$name" 2>/dev/null || true   # a pair left in the root namespace by an aborted set-up
    done
}

cleanup() {
    local pid
    for pid in "${PIDS[@]}"; do
        kill -TERM "$pid" 2>/dev/null || true
    done
    for pid in "${PIDS[@]}"; do
        wait "$pid" 2>/dev/null || true
    done
    remove_namespaces
    echo "logs: $LOG_DIR"
}
trap cleanup EXIT
trap 'exit 130' INT TERM  # exit runs the EXIT trap

# veth pair $1 (in namespace $2, address $3) <-> $4 (in namespace $5, address $6), /24
join() {
    ip link add "$1" type veth peer name "$4"
    ip link set "$1" netns "$2"
    ip link set "$4" netns "$5"
    ip -n "$2" addr add "$3/24" dev "$1"
    ip -n "$5" addr add "$6/24" dev "$4"
    ip -n "$2" link set "$1" up
    ip -n "$5" link set "$4" up
}

create_topology() {
    remove_namespaces
    ip netns add "$RSU_NS"
    ip netns add "$LINK_NS"
    ip netns add "$OBU_NS"
    join "$RSU_IF" "$RSU_NS" "$RSU_ADDR" "$LINK_RSU_IF" "$LINK_NS" "$LINK_RSU_ADDR"
    join "$LINK_OBU_IF" "$LINK_NS" "$LINK_OBU_ADDR" "$OBU_IF" "$OBU_NS" "$OBU_ADDR"
    ip -n "$OBU_NS" link set lo up  # for the local watcher only (see the top)
}

# start NAME NAMESPACE ARGS...: a service in its namespace, stdout and stderr to $LOG_DIR/NAME.*
start() {
    local name=$1 ns=$2
    shift 2
    ip netns exec "$ns" "$PYTHON" -m v2i "$name" "$@" >"$LOG_DIR/$name.out" 2>"$LOG_DIR/$name.err" &
    PIDS+=($!)
}

wait_ready() {
    local name=$1 deadline=$((SECONDS + STARTUP_S + 5))
    until grep -q '"event": "ready"' "$LOG_DIR/$name.out" 2>/dev/null; do
        if ((SECONDS >= deadline)); then
            echo "$name not ready; its stderr:" >&2
            cat "$LOG_DIR/$name.err" >&2
            exit 1
        fi
        sleep 0.1
    done
    echo "$name ready"
}

link_config() {
    # The RSU position feeds the distance-dependent channel; the scenario knows it.
    "$PYTHON" - "$SCENARIO" >"$LOG_DIR/link.yaml" <<'EOF'
import json, sys
from sim.scenario import load_scenario
p = load_scenario(sys.argv[1]).rsu.position
print(json.dumps({"rsu_position": [p.x, p.y]}))
EOF
}

main() {
    create_topology
    if ip netns exec "$RSU_NS" timeout 2 bash -c "exec 3<>/dev/tcp/$OBU_ADDR/7448" 2>/dev/null; then
        echo "the RSU namespace reaches the OBU directly: the link would not be the only path" >&2
        exit 1
    fi
    echo "topology up: $RSU_NS ($RSU_ADDR) <-> $LINK_NS ($LINK_RSU_ADDR, $LINK_OBU_ADDR) <-> $OBU_NS ($OBU_ADDR)"
    link_config
    local t0_ns=$(($(date +%s%N) + STARTUP_S * 1000000000))
    local common=(--scenario "$SCENARIO" --seed "$SEED" --start-at-ns "$t0_ns" --duration "$DURATION_S")
    start rsu "$RSU_NS" --listen "$RSU_EP" "${common[@]}"
    start obu "$OBU_NS" --listen "$OBU_EP" "${common[@]}"
    start link "$LINK_NS" --config "$LOG_DIR/link.yaml" --rsu-connect "$RSU_EP" --vehicle-connect "$OBU_EP" \
        --profile "$PROFILE" --seed "$SEED"
    wait_ready rsu
    wait_ready obu
    wait_ready link
    echo "watching fused output in $OBU_NS ..."
    # In the background and waited for: bash runs a trap only once its foreground child has
    # ended, while `wait` returns at once on a signal, so that SIGTERM cleans up promptly.
    ip netns exec "$OBU_NS" "$PYTHON" "$HERE/watch_fused.py" --connect "$OBU_EP" \
        --min-rsu-lists "$MIN_RSU_LISTS" --timeout-s "$((STARTUP_S + DURATION_S))" &
    PIDS+=($!)
    wait "${PIDS[-1]}"
}

main "$@"
