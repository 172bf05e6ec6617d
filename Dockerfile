# tagswarm: one image for every role (router, world, server, agent, tools).
#   docker build -t tagswarm .
#   docker run --rm tagswarm --help            # the ENTRYPOINT is the `tagswarm` CLI
#   docker compose up                          # see compose.yaml
# Every dependency is a pinned manylinux wheel from PyPI (pybullet renders with its
# CPU TinyRenderer, OpenCV is the headless build): no system packages are needed.
# No credentials in the image: Zenoh passwords (and TLS keys) are mounted at run time
# (compose secrets under /run/secrets, see docs/security.md); .dockerignore keeps
# deploy/secrets/ and key files out of the build context.  Processes run as the
# unprivileged user `tagswarm` (uid 10001), never as root.
FROM python:3.11-slim

ENV PYTHONUNBUFFERED=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1

WORKDIR /opt/tagswarm
# The pinned dependencies first, from pyproject.toml alone: a layer that a code (or README)
# change does not invalidate (a rebuild after editing the code takes seconds, not minutes).
COPY pyproject.toml ./
RUN python -c "import tomllib; print('\n'.join(tomllib.load(open('pyproject.toml', 'rb'))['project']['dependencies']))" \
        > /tmp/requirements.txt \
    && pip install -r /tmp/requirements.txt \
    && rm /tmp/requirements.txt \
    && useradd --create-home --uid 10001 --shell /usr/sbin/nologin tagswarm
# tagswarm/protocol, tagswarm/world, ... are relative symlinks to these folders (one installed
# name, tagswarm.*): COPY keeps them as links, and `pip install .` puts real files in the wheel.
COPY README.md ./
COPY protocol ./protocol
COPY world ./world
COPY agents ./agents
COPY server ./server
COPY tagswarm ./tagswarm
RUN pip install --no-deps .

USER tagswarm
WORKDIR /home/tagswarm
# the router's Zenoh endpoint (tagswarm router --listen tcp/0.0.0.0:7447)
EXPOSE 7447
ENTRYPOINT ["tagswarm"]
CMD ["--help"]
