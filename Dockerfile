FROM python:3.11-slim
WORKDIR /app
COPY pyproject.toml README.md ./
COPY driftlab ./driftlab
COPY migrations ./migrations
COPY alembic.ini* ./
RUN pip install --no-cache-dir .
ENTRYPOINT []
