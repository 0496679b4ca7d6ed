# The station daemon (`station serve`) in a container. The site config is mounted read-only at
# /etc/station/station.toml; the SQLite database lives in the volume /var/lib/station (set
# database_url = "sqlite:////var/lib/station/station.db" in the config). See docker-compose.yml.
FROM python:3.11-slim-bookworm

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    MPLCONFIGDIR=/tmp/matplotlib \
    STATION_HEALTH_URL=http://127.0.0.1:8080/api/health

WORKDIR /opt/station
COPY pyproject.toml README.md ./
COPY contracts ./contracts
COPY station ./station
COPY drivers ./drivers
COPY db ./db
COPY web ./web
COPY cli ./cli
# Serial boards and Modbus RTU adapters are group dialout on the host; the daemon never runs as root.
RUN pip install . \
    && useradd --system --uid 10001 --gid dialout --home-dir /var/lib/station --create-home station \
    && mkdir -p /etc/station \
    && rm -rf /opt/station/build

USER station
WORKDIR /var/lib/station
VOLUME ["/var/lib/station"]
EXPOSE 8080
# SIGTERM: the daemon switches the lamp off first, interrupts the batch, then exits.
STOPSIGNAL SIGTERM
HEALTHCHECK --interval=15s --timeout=5s --start-period=30s --retries=3 \
    CMD ["python", "-c", "import os, sys, urllib.request; r = urllib.request.urlopen(os.environ['STATION_HEALTH_URL'], timeout=4); sys.exit(0 if r.status == 200 else 1)"]
CMD ["station", "serve", "--config", "/etc/station/station.toml"]
