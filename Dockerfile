# One image for every posegrid process (router, source, slam-node, mapper, run); docker-compose.yml picks
# the subcommand per service. Build: docker build -t posegrid .
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    NUMBA_CACHE_DIR=/tmp/numba-cache

WORKDIR /opt/posegrid
COPY pyproject.toml README.md ./
COPY mapping ./mapping
COPY slam ./slam
COPY schemas ./schemas
COPY services ./services
# /var/lib/posegrid: where the mapper shards' stores go (docker-compose.yml mounts a volume there; a new volume
# takes this folder's owner, so the shards, running as posegrid, can write it)
RUN pip install . && useradd --create-home posegrid \
    && mkdir -p /var/lib/posegrid && chown posegrid:posegrid /var/lib/posegrid
USER posegrid

ENTRYPOINT ["posegrid"]
CMD ["--help"]
