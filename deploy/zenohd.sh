#!/usr/bin/env bash
# Builds the fleet's router, the real `zenohd` from crates.io, once, and prints its path.
# Cached under ${EMR_CACHE:-$HOME/.cache/emr-floam}/zenohd-VERSION-tcp-tls: later calls cost nothing.
# The version is the one the workspace's zenoh library is locked to (Cargo.lock). Only the TCP and
# TLS transports are built, the two the fleet uses (docker-compose.yml, deploy/systemd): zenoh's
# defaults add QUIC, UDP, WebSocket, Unix sockets and user/key authentication, compiled for nothing.
set -euo pipefail
cd "$(dirname "$0")/.."
version=$(awk '/^name = "zenoh"$/ { getline; gsub(/[^0-9.]/, ""); print; exit }' Cargo.lock)
root="${EMR_CACHE:-$HOME/.cache/emr-floam}/zenohd-$version-tcp-tls"
# EMR_ZENOHD_NO_BUILD=1: only say where it would be (the tests' locator).
if [ ! -x "$root/bin/zenohd" ] && [ -z "${EMR_ZENOHD_NO_BUILD:-}" ]; then
    echo "building zenohd $version into $root (once; about 4 min on 2 cores)" >&2
    cargo install zenohd --version "=$version" --locked --root "$root" --quiet \
        --no-default-features --features zenoh/transport_tcp,zenoh/transport_tls >&2
fi
echo "$root/bin/zenohd"
