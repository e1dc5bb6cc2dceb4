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
# Start: RSU and OBU run with --await-start, each reading its stdin from a FIFO this script holds
# open. When every service has printed its ready line (within READY_TIMEOUT_S, however busy the
# machine) and the watcher runs, one start line {"event": "start", "start_at_ns": T0} with
# T0 = now + START_LEAD_MS goes to both: all namespaces share this host's clock, so T0 means the
# same instant to each. Two real hosts do the same over ssh (README, "running on two hosts").
#
# ROUTERS=1: a `v2i router` host on each side; every service is a Zenoh client of its side's
# router (V2I_ZENOH_MODE=client), the link emulator a client of both:
#
#   v2i-rsu 10.10.1.1 <-> 10.10.1.2 v2i-rr 10.10.3.1 <-> 10.10.3.2 v2i-link
#           v2i-link 10.10.4.2 <-> 10.10.4.1 v2i-vr 10.10.2.1 <-> 10.10.2.2 v2i-obu
#   routers listen on tcp/<each of their addresses>:7447; the watcher connects to v2i-vr
#
#   sudo deploy/netns/run.sh                      # python3 on PATH must have v2i installed
#   sudo PYTHON=.venv/bin/python PROFILE=dsrc deploy/netns/run.sh
#   sudo PYTHON=.venv/bin/python ROUTERS=1 deploy/netns/run.sh
set -euo pipefail

PREFIX=${PREFIX:-v2i}
PYTHON=${PYTHON:-python3}
SCENARIO=${SCENARIO:-red-light-runner}
PROFILE=${PROFILE:-lte-v2x}
SEED=${SEED:-0}
DURATION_S=${DURATION_S:-30}      # scenario seconds the services run
READY_TIMEOUT_S=${READY_TIMEOUT_S:-120}  # every service must print its ready line within this
START_LEAD_MS=${START_LEAD_MS:-1500}  # scenario time zero this long after the start line (the OBU syncs from 1 s before)
MIN_RSU_LISTS=${MIN_RSU_LISTS:-20}  # fused lists with RSU objects to see before declaring success
ROUTERS=${ROUTERS:-0}             # 1: a router host on each side, the services its clients

RSU_NS=$PREFIX-rsu LINK_NS=$PREFIX-link OBU_NS=$PREFIX-obu RR_NS=$PREFIX-rr VR_NS=$PREFIX-vr
RSU_IF=$PREFIX-r0 LINK_RSU_IF=$PREFIX-l0 LINK_OBU_IF=$PREFIX-l1 OBU_IF=$PREFIX-o0
RR_IF=$PREFIX-rr1 VR_IF=$PREFIX-vr0 RR_RSU_IF=$PREFIX-rr0 VR_OBU_IF=$PREFIX-vr1
RSU_ADDR=10.10.1.1 LINK_RSU_ADDR=10.10.1.2 LINK_OBU_ADDR=10.10.2.1 OBU_ADDR=10.10.2.2
RSU_EP=tcp/$RSU_ADDR:7447 OBU_EP=tcp/$OBU_ADDR:7448
# ROUTERS=1: the RSU-side router 10.10.1.2 | 10.10.3.1, the vehicle-side one 10.10.4.1 | 10.10.2.1
RR_RSU_ADDR=10.10.1.2 RR_LINK_ADDR=10.10.3.1 LINK_RR_ADDR=10.10.3.2
VR_LINK_ADDR=10.10.4.1 VR_OBU_ADDR=10.10.2.1 LINK_VR_ADDR=10.10.4.2
ROUTER_PORT=7447

# Resolve before entering the namespaces: `ip netns exec` must run the very same interpreter.
PYTHON=$(command -v "$PYTHON")
PYTHON=$(readlink -f "$(dirname "$PYTHON")")/$(basename "$PYTHON")
HERE=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
LOG_DIR=$(mktemp -d "${TMPDIR:-/tmp}/v2i-netns.XXXXXX")
PIDS=()

remove_namespaces() {
    local name
    for name in "$RSU_NS" "$LINK_NS" "$OBU_NS" "$RR_NS" "$VR_NS"; do
        ip netns del "$name" 2>/dev/null || true  # takes the veth ends inside with it
    done
    for name in "$RSU_IF" "$OBU_IF" "$RR_IF" "$VR_IF"; do
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

create_routed_topology() {
    remove_namespaces
    local ns
    for ns in "$RSU_NS" "$RR_NS" "$LINK_NS" "$VR_NS" "$OBU_NS"; do
        ip netns add "$ns"
    done
    join "$RSU_IF" "$RSU_NS" "$RSU_ADDR" "$RR_RSU_IF" "$RR_NS" "$RR_RSU_ADDR"
    join "$RR_IF" "$RR_NS" "$RR_LINK_ADDR" "$LINK_RSU_IF" "$LINK_NS" "$LINK_RR_ADDR"
    join "$VR_IF" "$VR_NS" "$VR_LINK_ADDR" "$LINK_OBU_IF" "$LINK_NS" "$LINK_VR_ADDR"
    join "$VR_OBU_IF" "$VR_NS" "$VR_OBU_ADDR" "$OBU_IF" "$OBU_NS" "$OBU_ADDR"
}

# start NAME NAMESPACE ARGS...: a service in its namespace, stdout and stderr to $LOG_DIR/NAME.*,
# stdin from the FIFO $LOG_DIR/NAME.start, which this script holds open for writing (START_FDS[NAME])
# ($MODE: the services' Zenoh mode, peer or client)
declare -A START_FDS=()
start() {
    local name=$1 ns=$2 fd
    shift 2
    mkfifo "$LOG_DIR/$name.start"
    exec {fd}<>"$LOG_DIR/$name.start"  # read-write: opening it does not wait for the service
    START_FDS[$name]=$fd
    ip netns exec "$ns" env V2I_ZENOH_MODE="$MODE" "$PYTHON" -m v2i "$name" "$@" \
        <"$LOG_DIR/$name.start" >"$LOG_DIR/$name.out" 2>"$LOG_DIR/$name.err" &
    PIDS+=($!)
}

# start_services NAME...: time zero now + START_LEAD_MS, one start line to each service (then EOF)
start_services() {
    local t0_ns=$(($(date +%s%N) + START_LEAD_MS * 1000000)) name fd
    for name in "$@"; do
        fd=${START_FDS[$name]}
        printf '{"event": "start", "start_at_ns": %s}\n' "$t0_ns" >&"$fd"
        exec {fd}>&-
    done
    echo "started $* at $t0_ns ns ($START_LEAD_MS ms from now)"
}

# start_router NAME NAMESPACE ADDR...: `v2i router` listening on ADDR:$ROUTER_PORT for each ADDR
start_router() {
    local name=$1 ns=$2 addr listen=()
    shift 2
    for addr in "$@"; do
        listen+=(--listen "tcp/$addr:$ROUTER_PORT")
    done
    ip netns exec "$ns" "$PYTHON" -m v2i router "${listen[@]}" >"$LOG_DIR/$name.out" 2>"$LOG_DIR/$name.err" &
    PIDS+=($!)
}

wait_ready() {
    local name=$1 t0=$SECONDS
    echo "waiting for $name ..."
    until grep -q '"event": "ready"' "$LOG_DIR/$name.out" 2>/dev/null; do
        if ((SECONDS - t0 >= READY_TIMEOUT_S)); then
            echo "$name not ready after $READY_TIMEOUT_S s (READY_TIMEOUT_S); its stderr:" >&2
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
from v2i.sim.scenario import load_scenario
p = load_scenario(sys.argv[1]).rsu.position
print(json.dumps({"rsu_position": [p.x, p.y]}))
EOF
}

# refuse NS ADDR PORT: exit when namespace NS can open a TCP connection to ADDR:PORT (a bypass)
refuse() {
    if ip netns exec "$1" timeout 2 bash -c "exec 3<>/dev/tcp/$2/$3" 2>/dev/null; then
        echo "$1 reaches $2:$3 directly: the link would not be the only path" >&2
        exit 1
    fi
}

# watch ENDPOINT: the fused-output watcher in the OBU namespace; then RSU and OBU get their start
# line, and the watcher is waited for
watch() {
    echo "watching fused output in $OBU_NS ..."
    # In the background and waited for: bash runs a trap only once its foreground child has
    # ended, while `wait` returns at once on a signal, so that SIGTERM cleans up promptly.
    ip netns exec "$OBU_NS" env V2I_ZENOH_MODE="$MODE" "$PYTHON" "$HERE/watch_fused.py" --connect "$1" \
        --min-rsu-lists "$MIN_RSU_LISTS" --timeout-s "$((DURATION_S + 10))" &
    PIDS+=($!)
    local watcher=$!
    start_services rsu obu
    wait "$watcher"
}

run_peers() {
    MODE=peer
    create_topology
    refuse "$RSU_NS" "$OBU_ADDR" 7448
    echo "topology up: $RSU_NS ($RSU_ADDR) <-> $LINK_NS ($LINK_RSU_ADDR, $LINK_OBU_ADDR) <-> $OBU_NS ($OBU_ADDR)"
    link_config
    local common=(--scenario "$SCENARIO" --seed "$SEED" --await-start --duration "$DURATION_S")
    start rsu "$RSU_NS" --listen "$RSU_EP" "${common[@]}"
    start obu "$OBU_NS" --listen "$OBU_EP" "${common[@]}"
    start link "$LINK_NS" --config "$LOG_DIR/link.yaml" --rsu-connect "$RSU_EP" --vehicle-connect "$OBU_EP" \
        --profile "$PROFILE" --seed "$SEED"
    wait_ready rsu
    wait_ready obu
    wait_ready link
    watch "$OBU_EP"
}

run_routers() {
    MODE=client
    create_routed_topology
    echo "topology up: $RSU_NS ($RSU_ADDR) <-> $RR_NS ($RR_RSU_ADDR, $RR_LINK_ADDR) <-> $LINK_NS ($LINK_RR_ADDR," \
         "$LINK_VR_ADDR) <-> $VR_NS ($VR_LINK_ADDR, $VR_OBU_ADDR) <-> $OBU_NS ($OBU_ADDR)"
    start_router rsu-router "$RR_NS" "$RR_RSU_ADDR" "$RR_LINK_ADDR"
    start_router vehicle-router "$VR_NS" "$VR_LINK_ADDR" "$VR_OBU_ADDR"
    wait_ready rsu-router
    wait_ready vehicle-router
    refuse "$RSU_NS" "$VR_OBU_ADDR" "$ROUTER_PORT"
    refuse "$RR_NS" "$VR_LINK_ADDR" "$ROUTER_PORT"
    link_config
    local common=(--scenario "$SCENARIO" --seed "$SEED" --await-start --duration "$DURATION_S")
    # RSU and OBU are clients of their routers; they still need an address of their own to listen on.
    start rsu "$RSU_NS" --listen "$RSU_EP" --connect "tcp/$RR_RSU_ADDR:$ROUTER_PORT" "${common[@]}"
    start obu "$OBU_NS" --listen "$OBU_EP" --connect "tcp/$VR_OBU_ADDR:$ROUTER_PORT" "${common[@]}"
    start link "$LINK_NS" --config "$LOG_DIR/link.yaml" --rsu-connect "tcp/$RR_LINK_ADDR:$ROUTER_PORT" \
        --vehicle-connect "tcp/$VR_LINK_ADDR:$ROUTER_PORT" --profile "$PROFILE" --seed "$SEED"
    wait_ready rsu
    wait_ready obu
    wait_ready link
    watch "tcp/$VR_OBU_ADDR:$ROUTER_PORT"
}

main() {
    case "$ROUTERS" in
        0) run_peers ;;
        1) run_routers ;;
        *) echo "ROUTERS must be 0 or 1, got $ROUTERS" >&2; exit 2 ;;
    esac
}

main "$@"
