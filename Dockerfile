# Build stage: compile the release binary.
FROM rust:1-bookworm AS build
WORKDIR /src
COPY Cargo.toml Cargo.lock ./
COPY crates crates
COPY migrations migrations
COPY api api
COPY ui ui
COPY vendor vendor
RUN cargo build --release --locked --bin precond

# Runtime stage: a small image, a non-root user, the database on a volume.
FROM debian:bookworm-slim
RUN apt-get update \
 && apt-get install -y --no-install-recommends ca-certificates curl \
 && rm -rf /var/lib/apt/lists/* \
 && groupadd --system --gid 10001 precond \
 && useradd --system --create-home --uid 10001 --gid 10001 precond \
 && mkdir -p /data && chown precond:precond /data
COPY --from=build /src/target/release/precond /usr/local/bin/precond
USER precond
WORKDIR /data
VOLUME ["/data"]
ENV PRECOND_ADDR=0.0.0.0:8080 \
    PRECOND_DATABASE_URL=/data/precond.db \
    PRECOND_LOG_FORMAT=json \
    RUST_LOG=info
EXPOSE 8080
HEALTHCHECK --interval=15s --timeout=3s --start-period=10s --retries=3 \
  CMD curl -fsS http://127.0.0.1:8080/healthz || exit 1
STOPSIGNAL SIGTERM
ENTRYPOINT ["precond"]
CMD ["serve"]
