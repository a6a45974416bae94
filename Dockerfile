# driftlab: the API, the acquisition daemon and the command line in one image.
# Installed as a wheel (not editable): migrations and examples ship inside the package.
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1

WORKDIR /src
COPY pyproject.toml setup.py README.md ./
COPY driftlab ./driftlab
COPY migrations ./migrations
COPY examples ./examples
RUN pip install --no-cache-dir . \
    && rm -rf /src \
    && useradd --create-home --uid 10001 --shell /usr/sbin/nologin driftlab

# never run as root; the embedded SQLite default lives under this user's data directory
USER driftlab
WORKDIR /home/driftlab

# `driftlab serve` listens here (docker-compose.yml publishes it on 127.0.0.1 only)
EXPOSE 8765

HEALTHCHECK --interval=10s --timeout=5s --start-period=20s --retries=5 \
    CMD ["python", "-c", "import sys, urllib.request; sys.exit(urllib.request.urlopen('http://127.0.0.1:8765/health', timeout=4).status != 200)"]

# every container runs a driftlab subcommand: `docker run IMAGE db upgrade`, `... daemon --plan P`
ENTRYPOINT ["driftlab"]
CMD ["serve", "--host", "0.0.0.0", "--port", "8765"]
