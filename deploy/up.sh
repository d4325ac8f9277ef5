#!/usr/bin/env bash
# Builds every image of the fleet on this machine, without any image registry, and starts
# docker-compose.yml. The images are FROM scratch: binaries built on this host and the shared
# libraries they load (ldd), nothing else (no shell, no package manager).
#
#   deploy/up.sh                 # release build of emr-edge and emr-station, zenohd, images, up -d
#   EMR_BIN_DIR=target/debug deploy/up.sh    # use binaries already built there (the CI test does)
#
# Environment: EMR_BIN_DIR (where emr-edge and emr-station are; default: a release build),
# EMR_ZENOHD (the router binary; default: deploy/zenohd.sh builds and caches it), COMPOSE_PROJECT_NAME.
# Extra arguments go to `compose up -d`. With a registry, `docker compose up --build` builds the same
# images from deploy/Dockerfile and deploy/zenohd.Dockerfile instead.
set -euo pipefail
cd "$(dirname "$0")/.."

compose() {
    if docker compose version >/dev/null 2>&1; then docker compose "$@"; else docker-compose "$@"; fi
}

# The unprivileged user every container runs as (no /etc/passwd lookup needed: numeric).
EMR_UID=10001

if [ -z "${EMR_BIN_DIR:-}" ]; then
    echo "building emr-edge and emr-station (release)" >&2
    cargo build --release --locked -p edge -p station --bins
    # Where cargo put them: CARGO_TARGET_DIR or the build configuration may move target/.
    target=$(cargo metadata --format-version 1 --no-deps | sed -n 's/.*"target_directory":"\([^"]*\)".*/\1/p')
    EMR_BIN_DIR=${target:-target}/release
fi
zenohd_bin=${EMR_ZENOHD:-$(bash deploy/zenohd.sh)}
zenoh_version=$(awk '/^name = "zenoh"$/ { getline; gsub(/[^0-9.]/, ""); print; exit }' Cargo.lock)

# stage DIR BINARY...: DIR/root holds the binaries and every library they load, at the paths the
# dynamic loader looks for them.
stage() {
    local dir=$1
    shift
    mkdir -p "$dir/root/usr/local/bin" "$dir/root/tmp" "$dir/data"
    chmod 1777 "$dir/root/tmp"
    for bin in "$@"; do
        [ -x "$bin" ] || { echo "error: $bin is not an executable (EMR_BIN_DIR / EMR_ZENOHD)" >&2; exit 1; }
        cp -L "$bin" "$dir/root/usr/local/bin/"
        # "libm.so.6 => /lib/x86_64-linux-gnu/libm.so.6 (0x...)" and "/lib64/ld-linux-x86-64.so.2 (0x...)"
        ldd "$bin" | awk '$2 == "=>" && $3 ~ /^\// { print $3 } $1 ~ /^\// { print $1 }' | while read -r lib; do
            mkdir -p "$dir/root$(dirname "$lib")"
            cp -L "$lib" "$dir/root$lib"
        done
    done
}

# image TAG DIR: DIR/root owned by root, DIR/data by the unprivileged user (its volumes start so).
image() {
    local tag=$1 dir=$2
    cat >"$dir/Dockerfile" <<DOCKERFILE
FROM scratch
COPY root/ /
COPY --chown=$EMR_UID:$EMR_UID data/ /
USER $EMR_UID:$EMR_UID
WORKDIR /var/lib/emr
# Logs at info on stderr even without a terminal (docker logs).
ENV RUST_LOG=info
DOCKERFILE
    DOCKER_BUILDKIT=0 docker build --quiet --tag "$tag" "$dir" >/dev/null
    echo "built $tag ($(docker image inspect --format '{{.Size}}' "$tag" | awk '{ printf "%.0f MB", $1 / 1e6 }'))" >&2
}

work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

stage "$work/emr" "$EMR_BIN_DIR/emr-edge" "$EMR_BIN_DIR/emr-station"
mkdir -p "$work/emr/data/var/lib/emr/station" "$work/emr/data/etc/emr/fleet"
image emr-floam:latest "$work/emr"

stage "$work/zenohd" "$zenohd_bin"
mkdir -p "$work/zenohd/data/var/lib/emr" "$work/zenohd/data/etc/emr/fleet"
image "emr-zenohd:$zenoh_version" "$work/zenohd"

compose up -d --no-build "$@"
