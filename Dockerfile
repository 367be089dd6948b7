# Multi-stage build of `splatmark serve`. The runtime image carries Mesa's software Vulkan driver
# so that wgpu finds an adapter on machines without a GPU (workers then use the CPU backend).
#   docker build -t splatmark . && docker run -p 8080:8080 -v splatmark-data:/var/lib/splatmark splatmark
FROM rust:1.95-bookworm AS build
WORKDIR /src
COPY Cargo.toml Cargo.lock build.rs ./
COPY src ./src
COPY benches ./benches
COPY tests ./tests
COPY migrations ./migrations
COPY weights ./weights
COPY api ./api
COPY shaders ./shaders
RUN cargo build --release --locked --bin splatmark

FROM debian:bookworm-slim
RUN apt-get update \
 && apt-get install -y --no-install-recommends mesa-vulkan-drivers libvulkan1 ca-certificates curl \
 && rm -rf /var/lib/apt/lists/*
COPY --from=build /src/target/release/splatmark /usr/local/bin/splatmark
COPY deploy/splatmark.toml /etc/splatmark/splatmark.toml
RUN useradd --system --uid 10001 --create-home splatmark \
 && mkdir -p /var/lib/splatmark && chown splatmark /var/lib/splatmark
USER splatmark
WORKDIR /home/splatmark
VOLUME ["/var/lib/splatmark"]
EXPOSE 8080
ENV XDG_RUNTIME_DIR=/tmp
HEALTHCHECK --interval=30s --timeout=5s CMD curl -fsS http://127.0.0.1:8080/healthz || exit 1
ENTRYPOINT ["splatmark"]
CMD ["serve", "--config", "/etc/splatmark/splatmark.toml"]
