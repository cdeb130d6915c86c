# The platform's images, one target a role (docker-compose.yml builds them):
#   client    `bgrl login / jobs / models pull` and the Python client (no server packages)
#   api       the api (`bgrl up --only api`): no torch, pybullet or MNE
#   platform  the sim, EEG and learner services and the job workers; alone, `bgrl up`
#             runs the whole platform (the default target)
# Every target installs the versions the tests passed with (requirements.lock).
FROM python:3.11-slim AS base

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    BGRL_DATA_DIR=/data \
    BGRL_ARTIFACT_DIR=/artifacts

RUN useradd --create-home --uid 1000 bgrl \
    && mkdir -p /data /artifacts \
    && chown bgrl:bgrl /data /artifacts

WORKDIR /app
COPY pyproject.toml README.md requirements.lock ./
COPY services ./services
COPY benchmarks ./benchmarks
# The dashboard's static files: the api serves web/ from beside services/ (/app/web).
COPY web ./web

FROM base AS client
RUN pip install -c requirements.lock '.[client]'
USER bgrl
ENTRYPOINT ["bgrl"]
CMD ["--help"]

FROM base AS api
RUN pip install -c requirements.lock '.[api]'
USER bgrl
VOLUME ["/data", "/artifacts"]
EXPOSE 8000
CMD ["bgrl", "up", "--only", "api"]

FROM base AS platform
# CPU-only torch (the platform trains small MLPs and EEGNet on CPU): the lock's torch pin
# takes the CPU build.
RUN pip install --extra-index-url https://download.pytorch.org/whl/cpu \
    -c requirements.lock '.[worker]'
USER bgrl
VOLUME ["/data", "/artifacts"]
EXPOSE 8000 8001 8002 8003
# One service per container in compose; on its own the image runs the whole platform.
CMD ["bgrl", "up"]
