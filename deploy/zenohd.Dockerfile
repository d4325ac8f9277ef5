# The fleet's router, the real zenohd, for machines WITH an image registry (docker compose up --build).
# Without a registry, deploy/up.sh builds it with deploy/zenohd.sh and packs it FROM scratch.
# Keep the version equal to the zenoh library's in Cargo.lock.
FROM rust:1.95-bookworm AS build
# Only the two transports the fleet uses (deploy/zenohd.sh says why).
RUN cargo install zenohd --version =1.10.2 --locked --root /out \
    --no-default-features --features zenoh/transport_tcp,zenoh/transport_tls

FROM debian:bookworm-slim
RUN mkdir -p /etc/emr/fleet && chown 10001:10001 /etc/emr/fleet
COPY --from=build /out/bin/zenohd /usr/local/bin/
USER 10001:10001
