# facecast server image: Debian (bookworm) Python with Debian's PoCL OpenCL driver.
#   docker compose up -d          (see docker-compose.yml)
#   docker build -t facecast . && docker run -p 127.0.0.1:8000:8000 -v facecast-data:/data facecast
FROM python:3.11-slim-bookworm

# PoCL from Debian: the PoCL bundled in the PyOpenCL wheel cannot compile for some current CPUs.
RUN apt-get update \
 && DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends \
      pocl-opencl-icd ocl-icd-libopencl1 clinfo libsndfile1 \
 && rm -rf /var/lib/apt/lists/*

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    FACECAST_DATA_DIR=/data \
    FACECAST_CACHE=/data/cache

WORKDIR /src
COPY pyproject.toml setup.py README.md ./
COPY protocol ./protocol
COPY server ./server
COPY client ./client
RUN pip install . && rm -rf /src/build

RUN useradd --system --create-home --uid 10001 facecast \
 && mkdir -p /data && chown facecast:facecast /data
USER facecast
WORKDIR /home/facecast
VOLUME ["/data"]
EXPOSE 8000

HEALTHCHECK --interval=10s --timeout=3s --start-period=20s --retries=3 \
  CMD python -c "import urllib.request,sys; sys.exit(0 if urllib.request.urlopen('http://127.0.0.1:8000/healthz', timeout=2).status == 200 else 1)"

# Inside the container the server must listen on all interfaces; publish the port on the host's
# loopback (docker-compose.yml does) unless other machines should reach it.
CMD ["facecast", "serve", "--host", "0.0.0.0", "--allow-remote", "--port", "8000", "--data-dir", "/data"]
