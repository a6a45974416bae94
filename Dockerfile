FROM python:3.11-slim
WORKDIR /app
COPY pyproject.toml README.md alembic.ini ./
COPY driftlab ./driftlab
COPY migrations ./migrations
COPY examples ./examples
# Installed in place: the store finds migrations/ and the demo finds examples/ beside the package.
RUN pip install --no-cache-dir -e .
ENTRYPOINT []
