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
# Dependencies first, against stub sources (one per [[bench]] in Cargo.toml, which cargo
# insists on finding): this layer is rebuilt only when Cargo.toml, Cargo.lock, build.rs or the
# protos change, not on every source edit.
COPY Cargo.toml Cargo.lock build.rs ./
COPY proto ./proto
RUN mkdir -p src benches \
    && echo 'fn main() {}' > src/main.rs \
    && touch src/lib.rs \
    && grep -A1 '^\[\[bench\]\]' Cargo.toml | sed -n 's/^name = "\(.*\)"/\1/p' \
       | while read -r b; do echo 'fn main() {}' > "benches/$b.rs"; done \
    && cargo build --release --locked --bin murk \
    && rm -rf src target/release/murk target/release/deps/murk-* target/release/deps/libmurk-* \
       target/release/.fingerprint/murk-*
COPY models ./models
COPY src ./src
RUN cargo build --release --locked --bin murk \
    && cp target/release/murk /usr/local/bin/murk \
    && /usr/local/bin/murk --version

FROM ${RUNTIME_IMAGE}
LABEL org.opencontainers.image.title="murk" \
      org.opencontainers.image.description="gRPC service reconstructing depth and shape through fog, smoke and turbid water" \
      org.opencontainers.image.licenses="Apache-2.0" \
      org.opencontainers.image.source="https://github.com/murk/murk"
RUN groupadd --system --gid 10001 murk \
    && useradd --system --uid 10001 --gid murk --home-dir /var/lib/murk --create-home --shell /usr/sbin/nologin murk
COPY --from=builder /usr/local/bin/murk /usr/local/bin/murk
USER 10001:10001
WORKDIR /var/lib/murk
# A container listens on all interfaces; without MURK_AUTH_TOKENS_FILE murk refuses to start
# on them unless MURK_ALLOW_UNAUTHENTICATED is set (see README "Security and operations").
ENV MURK_ADDR=0.0.0.0:50051 \
    MURK_METRICS_ADDR=0.0.0.0:9090 \
    MURK_LOG_FORMAT=json
EXPOSE 50051 9090
HEALTHCHECK --interval=10s --timeout=5s --start-period=15s --retries=3 \
    CMD ["murk", "health", "--server", "http://127.0.0.1:50051", "--timeout-secs", "3"]
ENTRYPOINT ["murk"]
CMD ["serve"]
