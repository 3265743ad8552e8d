#!/usr/bin/env bash
# Builds stand-ins for the Dockerfile's base images where the public image registry cannot be
# reached (as on murk's build machines): a Debian bookworm root filesystem from debootstrap,
# imported as `murk-standin/debian:bookworm-slim`, a builder on top of it carrying this
# machine's Rust toolchain, `murk-standin/rust:bookworm`, and Debian's redis-server and nginx on
# the same base for deploy/docker-compose.yml (`murk-standin/redis:bookworm`,
# `murk-standin/nginx:bookworm`, and `murk-standin/prometheus:bookworm` for its observability
# profile). Then:
#
#   docker build --build-arg RUST_IMAGE=murk-standin/rust:bookworm \
#                --build-arg RUNTIME_IMAGE=murk-standin/debian:bookworm-slim -t murk:latest .
#
# Needs root, debootstrap and a running dockerd. The mirror is the first argument
# (default http://deb.debian.org/debian).
set -euo pipefail
mirror="${1:-http://deb.debian.org/debian}"
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT

rootfs="$work/rootfs"
debootstrap --variant=minbase bookworm "$rootfs" "$mirror"
# Keep the runtime base slim: no apt lists, docs or locales.
rm -rf "$rootfs"/var/lib/apt/lists/* "$rootfs"/usr/share/doc/* "$rootfs"/usr/share/man/* \
       "$rootfs"/usr/share/locale/*
tar -C "$rootfs" -c . | docker import - murk-standin/debian:bookworm-slim

# The builder: the runtime base plus a C toolchain and the Rust toolchain of this machine.
toolchain="$(rustc --print sysroot)"
cargo_bin="$(dirname "$(command -v cargo)")"
mkdir -p "$work/ctx/toolchain"
cp -a "$toolchain/." "$work/ctx/toolchain/"
# This machine's CA bundle, so cargo in the builder trusts what the host trusts (a TLS-inspecting
# proxy's CA, say).
cp "${SSL_CERT_FILE:-/etc/ssl/certs/ca-certificates.crt}" "$work/ctx/host-ca.crt"
cat > "$work/ctx/Dockerfile" <<'DOCKERFILE'
FROM murk-standin/debian:bookworm-slim
RUN apt-get update \
    && apt-get install -y --no-install-recommends gcc libc6-dev ca-certificates \
    && rm -rf /var/lib/apt/lists/*
COPY toolchain /usr/local/rust
COPY host-ca.crt /etc/ssl/certs/ca-certificates.crt
ENV PATH=/usr/local/rust/bin:/usr/local/cargo/bin:$PATH \
    CARGO_HOME=/usr/local/cargo
RUN mkdir -p /usr/local/cargo/bin && rustc --version && cargo --version
DOCKERFILE
docker build -t murk-standin/rust:bookworm "$work/ctx"
# The compose file's redis and nginx, from Debian's packages: the commands it runs
# (`redis-server …` in /data, `nginx -g 'daemon off;' -c …`) work on them unchanged.
mkdir -p "$work/redis" "$work/nginx"
cat > "$work/redis/Dockerfile" <<'DOCKERFILE'
FROM murk-standin/debian:bookworm-slim
RUN apt-get update \
    && apt-get install -y --no-install-recommends redis-server redis-tools \
    && rm -rf /var/lib/apt/lists/* \
    && mkdir -p /data && chown redis:redis /data
USER redis
WORKDIR /data
EXPOSE 6379
CMD ["redis-server"]
DOCKERFILE
docker build -t murk-standin/redis:bookworm "$work/redis"
cat > "$work/nginx/Dockerfile" <<'DOCKERFILE'
FROM murk-standin/debian:bookworm-slim
RUN apt-get update \
    && apt-get install -y --no-install-recommends nginx \
    && rm -rf /var/lib/apt/lists/*
EXPOSE 50051
CMD ["nginx", "-g", "daemon off;"]
DOCKERFILE
docker build -t murk-standin/nginx:bookworm "$work/nginx"
# The observability profile's Prometheus, from Debian's package, run as the official image runs
# it: the binary as the entrypoint (the compose file passes only flags), data in /prometheus.
# Grafana has no Debian package; the profile's grafana service needs the official image.
mkdir -p "$work/prometheus"
cat > "$work/prometheus/Dockerfile" <<'DOCKERFILE'
FROM murk-standin/debian:bookworm-slim
RUN apt-get update \
    && apt-get install -y --no-install-recommends prometheus \
    && rm -rf /var/lib/apt/lists/* \
    && mkdir -p /prometheus && chown prometheus:prometheus /prometheus
USER prometheus
WORKDIR /prometheus
EXPOSE 9090
ENTRYPOINT ["/usr/bin/prometheus"]
CMD ["--config.file=/etc/prometheus/prometheus.yml", "--storage.tsdb.path=/prometheus"]
DOCKERFILE
docker build -t murk-standin/prometheus:bookworm "$work/prometheus"
echo "stand-in images ready (cargo from ${cargo_bin})"
echo "compose with them: RUST_IMAGE=murk-standin/rust:bookworm \\"
echo "  RUNTIME_IMAGE=murk-standin/debian:bookworm-slim REDIS_IMAGE=murk-standin/redis:bookworm \\"
echo "  NGINX_IMAGE=murk-standin/nginx:bookworm PROMETHEUS_IMAGE=murk-standin/prometheus:bookworm \\"
echo "  docker-compose -p murk -f deploy/docker-compose.yml up -d --build"
