# The Property Service gateway as a container image.
#
#   podman build --format docker -t psgateway .        (or: docker build -t psgateway .)
#   podman run --rm -p 127.0.0.1:50051:50051 -p 127.0.0.1:8080:8080 psgateway   (plaintext: loopback only)
#
# PYTHON_IMAGE picks the base: any slim image with python3 (3.11 or newer) and its venv module.
# The default is the official slim image; a machine that cannot pull from a registry passes a base
# it made itself (tests/containers/setup.sh imports a minimal Debian with python3 as
# localhost/psgateway-base:bookworm). --format docker keeps the HEALTHCHECK (OCI images drop it).
ARG PYTHON_IMAGE=docker.io/library/python:3.11-slim-bookworm

# ---- stage 1: every wheel the gateway needs, its own included; nothing compiled -----------------
FROM ${PYTHON_IMAGE} AS build
ENV PIP_DISABLE_PIP_VERSION_CHECK=1 PIP_NO_CACHE_DIR=1 PYTHONDONTWRITEBYTECODE=1
RUN python3 -m venv /opt/build
WORKDIR /src
# The dependencies first, read from pyproject.toml, so that a change to the code alone reuses
# this layer. Binary wheels only: the image has no compiler, and needs none.
COPY pyproject.toml ./
RUN python3 -c "import tomllib; print('\n'.join(tomllib.load(open('pyproject.toml', 'rb'))['project']['dependencies']))" > requirements.txt \
 && /opt/build/bin/pip wheel --only-binary=:all: --wheel-dir /wheels -r requirements.txt
COPY README.md ./
COPY protos protos
COPY gateway gateway
COPY services services
COPY clients clients
RUN /opt/build/bin/pip wheel --no-deps --wheel-dir /wheels .

# ---- stage 2: the wheels installed into a venv (no index: only what stage 1 built) --------------
# COPY --from, not a RUN bind mount of stage 1: buildah keys its layer cache on what COPY brings,
# but not on a mount's content, and would reuse an install of older wheels.
FROM ${PYTHON_IMAGE} AS install
COPY --from=build /wheels /wheels
RUN python3 -m venv /opt/psgateway \
 && /opt/psgateway/bin/pip install --no-cache-dir --disable-pip-version-check --no-index \
      --find-links /wheels propertyservice-gateway \
 && /opt/psgateway/bin/pip uninstall --yes --disable-pip-version-check pip

# ---- stage 3: the venv alone on the same base, run by an unprivileged user ----------------------
FROM ${PYTHON_IMAGE}
LABEL org.opencontainers.image.title="psgateway" \
      org.opencontainers.image.description="Property Service gateway: Get, Set and Listen over gRPC and HTTP/JSON" \
      org.opencontainers.image.licenses="MIT" \
      io.psgateway.port.grpc="50051/tcp: propertyservice.v1.PropertyService, reflection, grpc.health.v1" \
      io.psgateway.port.http="8080/tcp: HTTP/JSON API, Server-Sent Events and the browser console" \
      io.psgateway.config="/etc/psgateway/gateway.toml: the config served (mount your own over it)" \
      io.psgateway.data="/var/lib/psgateway: working folder, writable by the gateway's user"
ENV PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1 PATH=/opt/psgateway/bin:$PATH
RUN groupadd --system --gid 10001 psgateway \
 && useradd --system --uid 10001 --gid psgateway --home-dir /var/lib/psgateway --create-home \
      --shell /usr/sbin/nologin psgateway
COPY --from=install /opt/psgateway /opt/psgateway
COPY containers/gateway.toml /etc/psgateway/gateway.toml
USER 10001:10001
WORKDIR /var/lib/psgateway
EXPOSE 50051/tcp 8080/tcp
# The gateway as a whole, through grpc.health.v1 (service ""): SERVING once every configured
# service has started, NOT_SERVING while it shuts down.
HEALTHCHECK --interval=10s --timeout=5s --start-period=30s --retries=3 \
  CMD ["python3", "-c", "import grpc, sys; from grpc_health.v1 import health_pb2 as h, health_pb2_grpc as g; s = g.HealthStub(grpc.insecure_channel('127.0.0.1:50051')).Check(h.HealthCheckRequest(service=''), timeout=4).status; sys.exit(0 if s == h.HealthCheckResponse.SERVING else 1)"]
ENTRYPOINT ["psgateway"]
CMD ["serve", "--config", "/etc/psgateway/gateway.toml"]
