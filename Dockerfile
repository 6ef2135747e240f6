# rayfarm: one image for the API service and the Celery workers.
#   docker compose up --scale worker=4
FROM python:3.11-slim

ENV PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    RAYFARM_DATA_DIR=/data \
    NUMBA_CACHE_DIR=/var/cache/numba

WORKDIR /app
COPY pyproject.toml README.md ./
COPY renderer ./renderer
COPY worker ./worker
COPY service ./service
RUN pip install .[postgres] \
 # Compile the Numba kernels into the image's cache, so workers start warm.
 && python -c "from renderer import warm_up; warm_up()"

VOLUME ["/data"]
EXPOSE 8000
CMD ["rayfarm", "serve", "--host", "0.0.0.0", "--port", "8000"]
