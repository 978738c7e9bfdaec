# syntax=docker/dockerfile:1
# rayd and rayctl in a slim Debian image. Build from the repository root:
#   docker build -t rayd .                                   # CPU backend
#   docker build -t rayd:gpu --build-arg VARIANT=gpu .       # + Vulkan loader and NVIDIA ICD (see deploy/README.md)
# The build stage runs deploy/docker/build.sh, which deploy/check.sh (CI) runs too; the entrypoint, environment and
# health check below are read and run by deploy/check.sh against the binaries it built.

ARG RUST_VERSION=1.95
ARG DEBIAN=bookworm

FROM rust:${RUST_VERSION}-slim-${DEBIAN} AS build
# Extra cargo features of rayd; empty builds the defaults (the CPU backend and the wgpu backend, feature `wgpu`).
ARG CARGO_FEATURES=""
WORKDIR /src
COPY . .
# No protoc needed: the contract is compiled with protox (pure Rust).
RUN --mount=type=cache,target=/usr/local/cargo/registry \
    --mount=type=cache,target=/src/target \
    CARGO_FEATURES="${CARGO_FEATURES}" PROFILE=release deploy/docker/build.sh /out

FROM debian:${DEBIAN}-slim AS run
# cpu: no Vulkan loader, so rayd lists only cpu:0. gpu: also the Vulkan loader and the NVIDIA ICD file, for the
# wgpu backend under the NVIDIA container runtime (which mounts the driver's libraries when the capabilities
# include `graphics`).
ARG VARIANT=cpu
RUN set -eux; \
    case "$VARIANT" in \
      cpu) ;; \
      gpu) apt-get update; \
           apt-get install -y --no-install-recommends libvulkan1; \
           rm -rf /var/lib/apt/lists/*; \
           mkdir -p /etc/vulkan/icd.d; \
           printf '%s\n' '{"file_format_version": "1.0.0",' \
             ' "ICD": {"library_path": "libGLX_nvidia.so.0", "api_version": "1.3"}}' \
             > /etc/vulkan/icd.d/nvidia_icd.json ;; \
      *) echo "VARIANT must be cpu or gpu, not $VARIANT" >&2; exit 1 ;; \
    esac; \
    groupadd --system --gid 10001 rayd; \
    useradd --system --uid 10001 --gid rayd --home-dir /data --shell /usr/sbin/nologin rayd; \
    mkdir -p /data /etc/rayd; \
    chown rayd:rayd /data
COPY --from=build /out/rayd /out/rayctl /usr/local/bin/

# Read by the NVIDIA container runtime (harmless without it): every GPU, with graphics (Vulkan) and compute.
ENV NVIDIA_VISIBLE_DEVICES=all \
    NVIDIA_DRIVER_CAPABILITIES=graphics,compute,utility
# rayd's own settings (flags win over them). Listening on every interface needs [[tenants]] in the configuration
# (mount one and set RAYD_CONFIG=/etc/rayd/rayd.toml) or RAYD_INSECURE=true.
ENV RAYD_LISTEN=0.0.0.0:50051 \
    RAYD_ADMIN_LISTEN=0.0.0.0:9464 \
    RAYD_DATA_DIR=/data

USER rayd:rayd
VOLUME ["/data"]
EXPOSE 50051 9464
HEALTHCHECK --interval=10s --timeout=5s --start-period=30s --retries=3 CMD ["rayctl", "health", "--timeout", "4"]
ENTRYPOINT ["rayd"]
