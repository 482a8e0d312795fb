# One CPU image for the API and the workers (no torch: fitting needs the train extra, so
# uploads are not refined here: TEXSPACE_AUTO_FIT has no effect without torch on the API).
#   docker build -t texspace .
#   docker run -p 8000:8000 texspace serve        # embedded: SQLite + SqliteHuey + /data
#   docker run texspace api | worker              # scale-out (see compose.yaml)
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1

# libgomp: OpenMP runtime some numeric wheels load; curl: the health check
RUN apt-get update \
    && apt-get install -y --no-install-recommends libgomp1 curl \
    && rm -rf /var/lib/apt/lists/*

RUN useradd --create-home --uid 10001 --user-group texspace \
    && mkdir -p /data && chown texspace:texspace /data

WORKDIR /src
# dependencies first (cached layer), then the code and the shipped model export
COPY pyproject.toml README.md ./
RUN mkdir -p service worker model && touch service/__init__.py worker/__init__.py model/__init__.py \
    && pip install . && pip uninstall -y texspace
COPY service ./service
COPY worker ./worker
COPY model ./model
# a regular (non-editable) install: the image runs from site-packages, with the model export
# (model/weights, the default TEXSPACE_MODEL_DIRS), migrations and web page as package data;
# the source folder is removed so nothing can import from it
RUN pip install --no-deps . && cd / && rm -rf /src \
    && python -c "import service.main, worker.runtime; from service.settings import PACKAGED_MODEL_DIR as d; \
assert all((d / n).is_file() for n in ('manifest.json', 'encoder.onnx', 'sampler.onnx', 'space.pt')), d"

WORKDIR /home/texspace
USER texspace
ENV TEXSPACE_DATA_DIR=/data \
    TEXSPACE_HOST=0.0.0.0 \
    TEXSPACE_PORT=8000
VOLUME ["/data"]
EXPOSE 8000
HEALTHCHECK --interval=30s --timeout=5s --start-period=30s \
    CMD curl -fsS "http://127.0.0.1:${TEXSPACE_PORT}/healthz" || exit 1
ENTRYPOINT ["texspace"]
CMD ["serve"]
