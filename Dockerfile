# Multi-stage build of the splatmark binary. The runtime image carries Mesa's software Vulkan
# driver so that wgpu finds an adapter on machines without a GPU.
FROM rust:1.95-bookworm AS build
WORKDIR /src
COPY Cargo.toml Cargo.lock ./
COPY src ./src
COPY benches ./benches
COPY tests ./tests
RUN cargo build --release --locked --bin splatmark

FROM debian:bookworm-slim
RUN apt-get update \
 && apt-get install -y --no-install-recommends mesa-vulkan-drivers libvulkan1 ca-certificates \
 && rm -rf /var/lib/apt/lists/*
COPY --from=build /src/target/release/splatmark /usr/local/bin/splatmark
RUN useradd --system --create-home splatmark
USER splatmark
WORKDIR /home/splatmark
ENTRYPOINT ["splatmark"]
CMD ["--help"]
