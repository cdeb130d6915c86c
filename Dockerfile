# The platform's image: api, sim, eeg and workers all run from it (see docker-compose.yml).
FROM python:3.11-slim

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
COPY pyproject.toml README.md ./
COPY services ./services
COPY benchmarks ./benchmarks
# The dashboard's static files: the api serves web/ from beside services/ (/app/web).
COPY web ./web
# CPU-only torch (the platform trains small MLPs and EEGNet on CPU).
RUN pip install --extra-index-url https://download.pytorch.org/whl/cpu .

USER bgrl
VOLUME ["/data", "/artifacts"]
EXPOSE 8000 8001 8002
# One service per container in compose; on its own the image runs the whole platform.
CMD ["bgrl", "up"]
