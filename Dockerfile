# DetMatch images, two targets of one multi-stage build:
#
#   serve  the gRPC labeling service: the `serve` extra only (onnxruntime, grpc; no torch),
#          a non-root user, port 50051 on all interfaces, a HEALTHCHECK through gRPC health.
#            docker build --target serve -t detmatch-serve .
#            docker run --rm -p 50051:50051 -e DETMATCH_TOKEN -v "$PWD/models:/models:ro" \
#                -v "$PWD/labels:/store" detmatch-serve
#          The store volume must be writable by uid 10001 (or pass --user).
#
#   train  every command (synth, train, predict, eval, detmatch-export, label, serve), with
#          the CPU build of torch; the default target.
#            docker build -t detmatch .
#            docker run --rm -v "$PWD/data:/data" detmatch synth --out /data/synth --frames 100
#          A CUDA build of torch instead (run it with `--gpus all`):
#            docker build --build-arg TORCH_VARIANT=cu128 -t detmatch:cuda .
ARG PYTHON_IMAGE=python:3.11-slim

# Shared by every stage: Python without bytecode or pip caches, and the unprivileged user.
FROM ${PYTHON_IMAGE} AS base
ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1
RUN groupadd --system --gid 10001 detmatch \
    && useradd --system --uid 10001 --gid detmatch --create-home --home-dir /home/detmatch detmatch

# The wheel: setup.py's build step generates the gRPC stubs from protos/ into it, and
# configs/ ships inside it as detmatch.configs (`--config tiny`).
FROM base AS wheel
WORKDIR /src
COPY pyproject.toml setup.py README.md ./
COPY configs ./configs
COPY protos ./protos
COPY detmatch ./detmatch
COPY export ./export
COPY serving ./serving
COPY retrain ./retrain
COPY commands ./commands
RUN pip wheel --no-deps --wheel-dir /wheels .

# The labeling service: no torch, no build tools.
FROM base AS serve
COPY --from=wheel /wheels /wheels
# The one package installed by name is the wheel built above (DL3013 cannot see its version).
# hadolint ignore=DL3013
RUN set -- /wheels/detmatch-*.whl \
    && pip install "$1[serve,postgres]" \
    && rm -rf /wheels \
    && mkdir -p /models /store \
    && chown detmatch:detmatch /store
USER 10001:10001
WORKDIR /home/detmatch
# `detmatch serve` binds all interfaces inside the container ($DETMATCH_HOST is --host's default).
ENV DETMATCH_HOST=0.0.0.0
EXPOSE 50051
# NOT_SERVING until a model version is loaded and warmed up, and while draining after SIGTERM.
HEALTHCHECK --interval=15s --timeout=10s --start-period=60s --retries=3 \
    CMD ["detmatch", "health", "--target", "127.0.0.1:50051", "--timeout-s", "5"]
ENTRYPOINT ["detmatch"]
# The bearer token comes from $DETMATCH_TOKEN (docker run -e / a Kubernetes secret); without
# one the server refuses to start, unless the command adds --no-auth.
CMD ["serve", "--repository", "/models", "--store", "/store", "--host", "0.0.0.0", "--port", "50051"]

# Everything, with torch from the PyTorch index: the CPU build unless TORCH_VARIANT names a
# CUDA one (cu126, cu128, ...). A plain `pip install torch` on Linux pulls the CUDA build.
FROM base AS train
ARG TORCH_VERSION=2.13.0
ARG TORCH_VARIANT=cpu
RUN pip install "torch==${TORCH_VERSION}" --index-url "https://download.pytorch.org/whl/${TORCH_VARIANT}"
COPY --from=wheel /wheels /wheels
# hadolint ignore=DL3013
RUN set -- /wheels/detmatch-*.whl \
    && pip install "$1[train,serve,postgres]" \
    && rm -rf /wheels \
    && mkdir -p /work \
    && chown detmatch:detmatch /work
USER 10001:10001
WORKDIR /work
ENV DETMATCH_HOST=0.0.0.0
EXPOSE 50051
ENTRYPOINT ["detmatch"]
CMD ["--help"]
