# The osrt image: one binary for the coordinator and the workers (see deploy/).
# Build: docker build -t ghcr.io/osrt/osrt:0.1.0 .
# protoc comes from the protoc-bin-vendored crate inside the build: nothing to install.

FROM rust:1-bookworm AS build
WORKDIR /src
# Dependencies first, so source edits do not rebuild them.
COPY Cargo.toml Cargo.lock ./
COPY crates crates
COPY proto proto
COPY src src
RUN cargo build --release --locked --bin osrt

FROM debian:bookworm-slim
# CA certificates for HTTPS object stores.
RUN apt-get update \
    && apt-get install -y --no-install-recommends ca-certificates \
    && rm -rf /var/lib/apt/lists/* \
    && useradd --uid 10001 --user-group --create-home osrt
COPY --from=build /src/target/release/osrt /usr/local/bin/osrt
USER 10001:10001
WORKDIR /home/osrt
ENTRYPOINT ["/usr/local/bin/osrt"]
CMD ["--help"]
