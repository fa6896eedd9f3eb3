# ASAC, CPU image (docs/deploy.md section 1). Build: `docker build -t asac .`; run: `docker run -v
# asac-data:/data asac gym/pendulum local --actors 1` (the arguments of main_ds.py; run folders go to the
# /data volume). `--target test` builds the same with the test extra and the tests. The GPU variant is
# Dockerfile.cuda; k8s/ runs both.
FROM python:3.11-slim AS base

# Runs as the numeric user below, on a read-only root file system too (k8s/): home and every cache
# under /tmp (numba compiles the sum tree into NUMBA_CACHE_DIR; without a writable one it cannot
# load), run folders under the /data volume (ASAC_MODEL_ROOT is --model_root's default).
ENV PYTHONUNBUFFERED=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PATH=/opt/venv/bin:$PATH \
    HOME=/tmp \
    XDG_CACHE_HOME=/tmp/cache \
    TORCH_HOME=/tmp/cache/torch \
    TORCHINDUCTOR_CACHE_DIR=/tmp/cache/torchinductor \
    TRITON_CACHE_DIR=/tmp/cache/triton \
    NUMBA_CACHE_DIR=/tmp/cache/numba \
    MPLCONFIGDIR=/tmp/cache/matplotlib \
    ASAC_MODEL_ROOT=/data/models

RUN groupadd --gid 10001 asac \
    && useradd --uid 10001 --gid 10001 --no-create-home --home-dir /tmp --shell /usr/sbin/nologin asac \
    && python3 -m venv /opt/venv \
    && mkdir -p /data/models \
    && chown -R 10001:10001 /data

WORKDIR /opt/asac

# The dependencies before the code, from the lock files only (exact versions and hashes; the Makefile's
# order): these layers are reused while only the code changes. torch's CPU build alone first.
# PIP_FIND_LINKS (a build argument, not kept in the image): a folder of wheels for builds that cannot
# reach the PyTorch index, e.g. `podman build -v /opt/wheels:/tmp/wheels:ro --build-arg
# PIP_FIND_LINKS=/tmp/wheels .` (docs/deploy.md section 1); the lock's hashes still decide.
ARG PIP_FIND_LINKS
COPY requirements/torch-cpu.txt requirements/runtime.txt requirements/
RUN python -m pip install --require-hashes --no-deps -r requirements/torch-cpu.txt
RUN python -m pip install --require-hashes -r requirements/runtime.txt

# The test extra and the whole checkout (tests, k8s/, the Makefile): `docker build --target test`.
FROM base AS test
COPY requirements/test.txt requirements/
RUN python -m pip install --require-hashes -r requirements/test.txt
COPY . .
RUN python -m pip install --no-deps --no-build-isolation -e .
USER 10001:10001
ENTRYPOINT ["python", "main_ds.py"]
CMD ["--help"]

# The runtime image (the default target): what main.py and main_ds.py import (cli.py the code they share), no test tooling.
FROM base AS runtime
COPY pyproject.toml README.md main.py main_ds.py cli.py ./
COPY algorithm algorithm/
COPY ds ds/
COPY envs envs/
COPY protos protos/
RUN python -m pip install --no-deps --no-build-isolation -e .
USER 10001:10001
VOLUME /data
# Exec form: python is PID 1 and gets SIGTERM itself; the roles save and exit on it.
ENTRYPOINT ["python", "main_ds.py"]
CMD ["--help"]
