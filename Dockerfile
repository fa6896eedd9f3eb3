# ASAC, CPU image. Build: `docker build -t asac .`; run a role: `docker run asac gym/pendulum replay`
# (the arguments of main_ds.py). The GPU variant is Dockerfile.cuda; k8s/ runs both.
FROM python:3.11-slim

ENV PYTHONUNBUFFERED=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PATH=/opt/venv/bin:$PATH

RUN groupadd --gid 10001 asac \
    && useradd --uid 10001 --gid 10001 --no-create-home --shell /usr/sbin/nologin asac \
    && python3 -m venv /opt/venv

WORKDIR /opt/asac

# The Makefile's install steps in its order (tests/test_k8s.py compares them): torch first and pinned,
# here from the CPU index so that no CUDA wheels come along (its layer stays cached while the code
# changes), then the checkout as an editable package with its test extra, as on a developer's machine.
RUN python -m pip install --upgrade pip
RUN python -m pip install --index-url https://download.pytorch.org/whl/cpu torch==2.13.0
COPY . .
RUN python -m pip install -e '.[test]'

USER 10001:10001
# Exec form: python is PID 1 and gets SIGTERM itself; the roles save and exit on it.
ENTRYPOINT ["python", "main_ds.py"]
CMD ["--help"]
