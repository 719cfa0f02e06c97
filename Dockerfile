# hrc-proactive operator server on the simulated cell.
#
#   docker build -t hrc-proactive .
#   docker run --rm -p 127.0.0.1:8000:8000 -p 127.0.0.1:8080:8080 -v hrc-data:/data hrc-proactive
#
# The operator token is generated at the first start, printed to the log and stored in the volume
# (/data/api_token, mode 0600); set HRC_API_TOKEN to choose it. API docs: http://localhost:8000/docs,
# 3D view: http://localhost:8080. For a real UR5e set HRC_ROBOT=rtde and HRC_ROBOT_HOST.
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1

# libgomp1: OpenMP runtime of torch's CPU kernels; curl-free health check uses Python.
RUN apt-get update \
    && apt-get install -y --no-install-recommends libgomp1 \
    && rm -rf /var/lib/apt/lists/*

# torch first, CPU-only, from the PyTorch CPU index (no CUDA packages); then the project.
RUN pip install --index-url https://download.pytorch.org/whl/cpu "torch==2.13.0"

WORKDIR /opt/hrc
# Dependencies change less often than the code: install them in their own layer.
COPY pyproject.toml README.md ./
RUN mkdir -p app && touch app/__init__.py \
    && pip install . \
    && pip uninstall -y hrc-proactive \
    && rm -rf app build *.egg-info

COPY alembic.ini ./
COPY app ./app
# The migrations ship inside the package (app/migrations); the image installs it editable like the set-up.
RUN pip install --no-deps -e . \
    && python -c "import app.api.app, app.study.db; assert app.study.db.MIGRATIONS_DIR.joinpath('env.py').is_file()"

ENV HOME=/data \
    NUMBA_CACHE_DIR=/opt/hrc/numba-cache \
    HRC_DATA_DIR=/data \
    HRC_CACHE_DIR=/data/cache \
    MPLCONFIGDIR=/data/.matplotlib \
    HRC_HOST=0.0.0.0 \
    HRC_PORT=8000 \
    HRC_VISER_PORT=8080 \
    HRC_ROBOT=sim \
    HRC_HUMAN_SOURCE=sim

# The roadmap of the shipped cell is built now, into the volume's initial content (a new volume gets a copy),
# so that the first start does not build it; it stays writable for another cell. A short headless trial
# compiles the numba kernels (servo loop, planner checks, forecast) into NUMBA_CACHE_DIR, so that no start
# pays their first compile (about a minute); the cache stays writable for kernels it did not reach.
RUN groupadd --system --gid 10001 hrc \
    && useradd --system --uid 10001 --gid hrc --home-dir /data --shell /usr/sbin/nologin hrc \
    && mkdir -p /data/cache "$NUMBA_CACHE_DIR" \
    && python -c "from app.config import load_workcell; from app.control.engine import PlanningStack; PlanningStack.for_cell(load_workcell())" \
    && hrc simulate --method proactive --duration 3 --seed 1 --json \
    && chown -R hrc:hrc /data "$NUMBA_CACHE_DIR"

VOLUME ["/data"]
USER hrc
EXPOSE 8000 8080

HEALTHCHECK --interval=30s --timeout=5s --start-period=120s --retries=3 \
    CMD ["python", "-c", "import os, sys, urllib.request; port = os.environ.get('HRC_PORT', '8000'); r = urllib.request.urlopen(f'http://127.0.0.1:{port}/api/health', timeout=4); sys.exit(0 if r.status == 200 else 1)"]

# exec form: hrc is PID 1 and receives SIGTERM directly (robot stopped first, then the database closed)
STOPSIGNAL SIGTERM
CMD ["hrc", "serve", "--host", "0.0.0.0"]
