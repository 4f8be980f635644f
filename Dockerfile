# One image for the API and the workers of docker-compose.yml.
#
# torch comes from the PyTorch wheel index picked by TORCH_INDEX_URL: the CUDA build for GPU workers (the
# default), or the CPU build for an API-only image:
#   docker build -t neudf .
#   docker build -t neudf-cpu --build-arg TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu .
# The version matches the pin in pyproject.toml, so `pip install .` keeps the build installed here.
FROM python:3.11-slim-bookworm

# libusb: open3d's wheel does not import without it; libgomp: OpenMP for open3d and pycolmap.
RUN apt-get update \
    && apt-get install -y --no-install-recommends libusb-1.0-0 libgomp1 libglib2.0-0 \
    && rm -rf /var/lib/apt/lists/*

ARG TORCH_VERSION=2.13.0
ARG TORCH_INDEX_URL=https://download.pytorch.org/whl/cu128
RUN pip install --no-cache-dir "torch==${TORCH_VERSION}" --index-url "${TORCH_INDEX_URL}"

WORKDIR /app
COPY pyproject.toml README.md ./
COPY neudf_core ./neudf_core
COPY worker ./worker
COPY service ./service
COPY web ./web
RUN pip install --no-cache-dir .

# Jobs, uploads and (without NEUDF_DATABASE_URL) the SQLite store live here: share it between the API and
# the workers (a named volume on one host, a network file system across hosts).
ENV NEUDF_DATA_DIR=/data \
    GRADIO_ANALYTICS_ENABLED=False \
    PYTHONUNBUFFERED=1
VOLUME /data
EXPOSE 8000

CMD ["neudf", "serve", "--host", "0.0.0.0", "--port", "8000"]
