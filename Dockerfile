# The ra2vipas services (orchestrator, learner, sensors, controller, rig, router): one image,
# the command picks the service, the environment configures it (see docker-compose.yml and
# docs/deployment.md).
#
#   docker build -t ra2vipas .
#   docker run --rm ra2vipas ra2vipas --help
FROM python:3.11-slim

ENV PYTHONUNBUFFERED=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    NUMBA_CACHE_DIR=/var/cache/ra2vipas/numba

WORKDIR /src
COPY pyproject.toml README.md constraints.txt ./
COPY ra2vipas ./ra2vipas
COPY services ./services
COPY cli ./cli
RUN pip install -c constraints.txt . \
    && rm -rf /src \
    && useradd --system --uid 10001 --create-home --home-dir /home/ra2vipas ra2vipas \
    && mkdir -p /data /models "$NUMBA_CACHE_DIR" \
    && chown ra2vipas:ra2vipas /data /models "$NUMBA_CACHE_DIR"

USER ra2vipas
WORKDIR /home/ra2vipas
# Compile the controller's numba kernels once, at build time, into the image's cache: a rig
# container is ready seconds after it starts.
RUN python -c "from ra2vipas.services.controller.node import warm_up; warm_up()"

EXPOSE 8080
CMD ["ra2vipas", "--help"]
