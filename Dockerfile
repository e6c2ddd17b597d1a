# The stage image: every cvxnav stage (and the monitor) runs from it with a different command.
# compose.yaml builds it as ${CVXNAV_IMAGE:-cvxnav:latest}; a swapped stage may use any other image.
FROM python:3.11-slim
WORKDIR /src
COPY pyproject.toml README.md ./
COPY cvxnav ./cvxnav
COPY schemas ./schemas
COPY services ./services
COPY sim ./sim
RUN pip install --no-cache-dir . && rm -rf /src
WORKDIR /work
# compose stops containers with SIGTERM; every stage shuts down cleanly on it.
STOPSIGNAL SIGTERM
CMD ["cvxnav", "--help"]
