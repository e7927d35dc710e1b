# One image for every fmapping service (io play / view / record, tracker, mapper).
#
#   docker build -t fmapping:cpu .                                    # CPU (default)
#   docker build -t fmapping:gpu --build-arg TORCH_INDEX=https://download.pytorch.org/whl/cu128 .
#
# torch comes first from the PyTorch index (the CPU wheel is ~200 MB; the default PyPI
# wheel would pull the multi-GB CUDA stack), then `pip install .` sees it satisfied.
FROM python:3.11-slim

ARG TORCH_VERSION=2.13.0
ARG TORCH_INDEX=https://download.pytorch.org/whl/cpu
# the zenoh release of the router image (docker-compose.yml passes the same ZENOH_VERSION to both)
ARG ZENOH_VERSION=1.10.2

ENV PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    FMAPPING_LOG=INFO

# libgomp: OpenMP runtime used by torch / opencv CPU kernels
RUN apt-get update \
    && apt-get install -y --no-install-recommends libgomp1 \
    && rm -rf /var/lib/apt/lists/*

RUN useradd --create-home --uid 1000 fmapping
WORKDIR /app

RUN pip install "torch==${TORCH_VERSION}" --index-url "${TORCH_INDEX}"

COPY pyproject.toml README.md ./
COPY fmapping ./fmapping
COPY services ./services
COPY examples ./examples
RUN pip install . "eclipse-zenoh==${ZENOH_VERSION}" \
    && python -c "import fmapping, services, zenoh, msgpack, rerun"

# owned by the service user before VOLUME: a fresh named volume mounted there starts with this owner
RUN mkdir -p /data /out && chown fmapping:fmapping /data /out
USER fmapping
VOLUME ["/data", "/out"]
# each compose service sets its own command, e.g. python -m services.mapper --help
CMD ["python", "-m", "services.io", "--help"]
