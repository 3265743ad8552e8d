# murk: multi-stage build. The base images are build arguments so that a registry mirror, a
# pinned digest or a locally built stand-in (deploy/stand-in-images.sh) can replace them.
ARG RUST_IMAGE=rust:1.95-slim-bookworm
ARG RUNTIME_IMAGE=debian:bookworm-slim

FROM ${RUST_IMAGE} AS builder
SHELL ["/bin/bash", "-o", "pipefail", "-c"]
WORKDIR /src
# Without debug info and symbols the binary shrinks from ~300 MB to a few tens.
ENV CARGO_PROFILE_RELEASE_DEBUG=0 \
    CARGO_PROFILE_RELEASE_STRIP=symbols \
    CARGO_TERM_COLOR=never
# Dependencies first, against stub sources (cargo insists on finding every member's targets,
# [[bench]] files included): this layer is rebuilt only when a manifest, Cargo.lock, build.rs or
# the protos change, not on every source edit.
COPY Cargo.toml Cargo.lock ./
COPY crates/murk/Cargo.toml crates/murk/Cargo.toml
COPY crates/murk-server/Cargo.toml crates/murk-server/build.rs crates/murk-server/
COPY proto ./proto
RUN for c in murk murk-server; do \
        mkdir -p "crates/$c/src" "crates/$c/benches" \
        && touch "crates/$c/src/lib.rs" \
        && grep -A1 '^\[\[bench\]\]' "crates/$c/Cargo.toml" | sed -n 's/^name = "\(.*\)"/\1/p' \
           | while read -r b; do echo 'fn main() {}' > "crates/$c/benches/$b.rs"; done; \
    done \
    && echo 'fn main() {}' > crates/murk-server/src/main.rs \
    && cargo build --release --locked -p murk-server --bin murk \
    && rm -rf crates/murk/src crates/murk-server/src target/release/murk \
       target/release/deps/murk-* target/release/deps/libmurk-* target/release/deps/murk_server-* \
       target/release/deps/libmurk_server-* target/release/.fingerprint/murk-*
COPY crates/murk/models ./crates/murk/models
COPY crates/murk/src ./crates/murk/src
COPY crates/murk-server/src ./crates/murk-server/src
RUN cargo build --release --locked -p murk-server --bin murk \
    && cp target/release/murk /usr/local/bin/murk \
    && /usr/local/bin/murk --version

FROM ${RUNTIME_IMAGE}
LABEL org.opencontainers.image.title="murk" \
      org.opencontainers.image.description="gRPC service reconstructing depth and shape through fog, smoke and turbid water" \
      org.opencontainers.image.licenses="Apache-2.0" \
      org.opencontainers.image.source="https://github.com/murk/murk"
# CA certificates: `rediss://` verifies Redis against the system's trust store unless
# MURK_REDIS_CA_FILE names a private CA.
RUN apt-get update \
    && apt-get install -y --no-install-recommends ca-certificates \
    && rm -rf /var/lib/apt/lists/*
RUN groupadd --system --gid 10001 murk \
    && useradd --system --uid 10001 --gid murk --home-dir /var/lib/murk --create-home --shell /usr/sbin/nologin murk
COPY --from=builder /usr/local/bin/murk /usr/local/bin/murk
USER 10001:10001
WORKDIR /var/lib/murk
# A container listens on all interfaces; without MURK_AUTH_TOKENS_FILE murk refuses to start
# on them unless MURK_ALLOW_UNAUTHENTICATED is set (see docs/operations.md).
ENV MURK_ADDR=0.0.0.0:50051 \
    MURK_METRICS_ADDR=0.0.0.0:9090 \
    MURK_LOG_FORMAT=json
EXPOSE 50051 9090
HEALTHCHECK --interval=10s --timeout=5s --start-period=15s --retries=3 \
    CMD ["murk", "health", "--server", "http://127.0.0.1:50051", "--timeout-secs", "3"]
ENTRYPOINT ["murk"]
CMD ["serve"]
