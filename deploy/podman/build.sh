#!/usr/bin/env bash
# Build the v2i image with podman, with no registry and no network inside the build:
#
#   1. a Debian bookworm base (minbase + python3.11 + venv) made with debootstrap from the host's
#      Debian mirror, kept as a tarball and imported with `podman import` as $V2I_BASE_IMAGE;
#   2. wheels built on the host for the project (from the working tree: pyproject.toml, README.md,
#      src/) and for every dependency, pinned to the versions of the Python that runs this script
#      (its `pip freeze`), so that the image runs what the tests ran;
#   3. `podman build -f deploy/Dockerfile`: FROM the base, `pip install --no-index` from the wheels
#      (bind-mounted into the RUN step, so that no wheel stays in a layer).
#
# Idempotent: the base tarball, the imported base and the dependency wheels are reused from the
# cache ($V2I_PODMAN_CACHE, default ~/.cache/v2i-podman); the project's wheel is rebuilt every time.
# Needs root (debootstrap, rootful podman), debootstrap, podman, runc, and a host Python 3.11 with
# pip and the project's dependencies installed (default: the repository's .venv).
#
#   sudo deploy/podman/build.sh                      # -> v2i:latest
#   sudo deploy/podman/build.sh --prometheus         # also v2i-prometheus:latest (Debian's prometheus)
#   sudo V2I_IMAGE=v2i:dev REBUILD_BASE=1 deploy/podman/build.sh
set -euo pipefail

REPO=$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)
CACHE=${V2I_PODMAN_CACHE:-$HOME/.cache/v2i-podman}
IMAGE=${V2I_IMAGE:-v2i:latest}
BASE_IMAGE=${V2I_BASE_IMAGE:-v2i-base:bookworm}
PROMETHEUS_IMAGE=${V2I_PROMETHEUS_IMAGE:-v2i-prometheus:latest}
SUITE=${DEBIAN_SUITE:-bookworm}
MIRROR=${DEBIAN_MIRROR:-http://deb.debian.org/debian}
PYTHON=${PYTHON:-$REPO/.venv/bin/python}
[ -x "$PYTHON" ] || PYTHON=python3
# podman as it runs on these machines (see deploy/README.md): runc, cgroupfs, ulimits we may set.
PODMAN=(podman --runtime runc --cgroup-manager cgroupfs)
ULIMITS=(--ulimit nofile=1024:1024 --ulimit nproc=4096:4096)

log() { printf '[build.sh %(%H:%M:%S)T] %s\n' -1 "$*" >&2; }

# A root file system as a tarball: debootstrap minbase + PACKAGES (comma-separated). Documentation,
# man pages, locales and apt's lists are dropped: nothing in the images reads them.
build_rootfs_tarball() {
    local tarball=$1 packages=$2 rootfs="$CACHE/rootfs.tmp"
    rm -rf "$rootfs"
    log "debootstrap $SUITE minbase + $packages from $MIRROR"
    debootstrap --variant=minbase --include="$packages" "$SUITE" "$rootfs" "$MIRROR" >"$CACHE/debootstrap.log"
    chroot "$rootfs" apt-get clean
    rm -rf "$rootfs"/var/lib/apt/lists/* "$rootfs"/usr/share/doc/* "$rootfs"/usr/share/man/* \
           "$rootfs"/usr/share/info/* "$rootfs"/usr/share/locale/* "$rootfs"/var/log/*.log \
           "$rootfs"/var/cache/debconf/*-old
    tar --numeric-owner -C "$rootfs" -cf "$tarball.part" .
    mv "$tarball.part" "$tarball"
    rm -rf "$rootfs"
}

# IMAGE from the tarball $CACHE/NAME.tar of minbase + PACKAGES, both made when missing (both again
# with REBUILD_BASE=1); further arguments are `podman import --change` instructions.
ensure_imported() {
    local image=$1 name=$2 packages=$3 tarball="$CACHE/$2.tar" change changes=()
    shift 3
    for change in "$@"; do changes+=(--change "$change"); done
    if [ -n "${REBUILD_BASE:-}" ]; then
        rm -f "$tarball"
        "${PODMAN[@]}" image rm "$image" >/dev/null 2>&1 || true
    fi
    [ -f "$tarball" ] || build_rootfs_tarball "$tarball" "$packages"
    if ! "${PODMAN[@]}" image exists "$image"; then
        log "podman import $tarball as $image"
        "${PODMAN[@]}" import "${changes[@]}" "$tarball" "$image" >/dev/null
    fi
}

# Wheels for the project and its dependencies in $CACHE/context/wheels. The dependencies are
# constrained to what $PYTHON has installed; wheels already in the folder are reused, not fetched.
build_wheels() {
    local wheels=$1 src="$CACHE/src.tmp" constraints="$CACHE/constraints.txt"
    rm -rf "$src" && mkdir -p "$src" "$wheels"
    # A copy of what the package is built from, so that the build leaves nothing in the checkout.
    cp "$REPO/pyproject.toml" "$REPO/README.md" "$src/"
    tar -C "$REPO" --exclude=__pycache__ --exclude='*.egg-info' --exclude='*.pyc' -cf - src | tar -C "$src" -xf -
    "$PYTHON" -m pip freeze --exclude-editable | grep -v -i '^v2i[= @]' >"$constraints"
    rm -f "$wheels"/v2i-*.whl
    log "pip wheel (project + dependencies) -> $wheels"
    "$PYTHON" -m pip wheel --quiet --no-cache-dir --find-links "$wheels" -c "$constraints" -w "$wheels" "$src" \
        2> >(grep -v 'is ignored: it is neither a file nor a directory' >&2)
    rm -rf "$src"
}

# The image this script built last time under $IMAGE, once the new build took its tag: removed
# when nothing else tags it and no container uses it (each build would otherwise leave ~700 MB).
remove_if_dangling() {
    local id=$1
    [ -n "$id" ] || return 0
    [ "$id" != "$("${PODMAN[@]}" image inspect --format '{{.Id}}' "$IMAGE")" ] || return 0
    [ "$("${PODMAN[@]}" image inspect --format '{{len .RepoTags}}' "$id" 2>/dev/null)" = 0 ] || return 0
    [ -z "$("${PODMAN[@]}" ps -a --quiet --filter "ancestor=$id")" ] || return 0
    log "removing the previous, now untagged $IMAGE (${id:0:12})"
    "${PODMAN[@]}" image rm "$id" >/dev/null
}

# Debian's prometheus in its own image, the same way (no registry): for the compose file's
# "prometheus" service. Its configuration is mounted at run time (deploy/prometheus/).
ensure_prometheus() {
    ensure_imported "$PROMETHEUS_IMAGE" "prometheus-$SUITE" prometheus \
        'USER prometheus' 'WORKDIR /var/lib/prometheus' 'EXPOSE 9090' 'ENTRYPOINT ["/usr/bin/prometheus"]' \
        'CMD ["--config.file=/etc/prometheus/prometheus.yml", "--storage.tsdb.path=/var/lib/prometheus/metrics2"]'
}

main() {
    local start_s=$SECONDS context="$CACHE/context"
    mkdir -p "$CACHE" "$context"
    case "${1:-}" in
        "") ;;
        --prometheus) ensure_prometheus ;;
        *) echo "usage: $0 [--prometheus]" >&2; exit 2 ;;
    esac
    # The services' base: python3 is 3.11 in bookworm; venv brings ensurepip's wheels.
    ensure_imported "$BASE_IMAGE" "base-$SUITE" python3,python3-venv 'CMD ["/bin/bash"]'
    build_wheels "$context/wheels"
    cp "$REPO/deploy/netns/watch_fused.py" "$context/watch_fused.py"
    rm -rf "$context/zenoh" && cp -r "$REPO/deploy/zenoh" "$context/zenoh"
    local previous_id
    previous_id=$("${PODMAN[@]}" image inspect --format '{{.Id}}' "$IMAGE" 2>/dev/null || true)
    # --layers=false: buildah's layer cache keys a RUN step on its text, not on what a --mount
    # brings in, so a cached install step would keep the previous project wheel.
    log "podman build $IMAGE (FROM $BASE_IMAGE, no network)"
    "${PODMAN[@]}" build "${ULIMITS[@]}" --layers=false --network none --pull=never --build-arg "BASE=$BASE_IMAGE" \
        -f "$REPO/deploy/Dockerfile" -t "$IMAGE" "$context"
    remove_if_dangling "$previous_id"
    log "built $IMAGE in $((SECONDS - start_s)) s: $("${PODMAN[@]}" image inspect --format '{{.Size}}' "$IMAGE") bytes"
}

main "$@"
