# The app as one image: `sepoa serve` (web server), `sepoa worker` (trainer), `sepoa train`, ...
# docker-compose.yml runs it; alone:  docker build -t sepoa . && docker run --rm sepoa --help
#
# CPU by default: torch comes from PyTorch's CPU-only index, so no CUDA packages (several GB) are
# downloaded, and MuJoCo renders clips through Mesa's EGL (llvmpipe). For a GPU worker image:
#   docker build --build-arg TORCH_INDEX_URL=https://download.pytorch.org/whl/cu126 -t sepoa:gpu .
# (a CUDA build of torch; or TORCH_INDEX_URL=https://pypi.org/simple for PyPI's default CUDA
# build), and run it with the NVIDIA container toolkit, giving the container the GPU with the
# `graphics` driver capability so MUJOCO_GL=egl uses the GPU's EGL (see docker-compose.yml).
FROM python:3.11-slim-bookworm

# Off-screen MuJoCo rendering: EGL (GPU or Mesa llvmpipe) and OSMesa as the fallback; the same
# libraries scripts/setup.sh installs. imageio-ffmpeg brings its own ffmpeg.
RUN apt-get update \
    && apt-get install -y --no-install-recommends \
        libegl1 libegl-mesa0 libgl1-mesa-dri libosmesa6 libglfw3 \
    && rm -rf /var/lib/apt/lists/*

ENV PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    MUJOCO_GL=egl

ARG TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu
ARG TORCH_SPEC="torch>=2.4,<2.14"
# torch first, from its own index: the project's requirement is then already met and pip does
# not pull PyPI's CUDA build.
RUN pip install --index-url "$TORCH_INDEX_URL" "$TORCH_SPEC"

WORKDIR /app
# The dependencies from pyproject.toml alone, in a layer of their own, so a code change does not
# reinstall MuJoCo, dm_control and the rest.
COPY pyproject.toml README.md alembic.ini ./
RUN python -c "import tomllib; p = tomllib.load(open('pyproject.toml', 'rb'))['project']; \
print('\n'.join(p['dependencies'] + p['optional-dependencies']['postgres']))" \
        > /tmp/requirements.txt \
    && pip install -r /tmp/requirements.txt \
    && rm /tmp/requirements.txt

COPY sepoa ./sepoa
COPY experiments ./experiments
COPY figures ./figures
COPY trainer ./trainer
COPY labelqueue ./labelqueue
COPY labelstats ./labelstats
COPY rundata ./rundata
COPY crowdstudy ./crowdstudy
COPY externalruns ./externalruns
COPY runviews ./runviews
COPY server ./server
COPY runvocab ./runvocab
COPY web ./web
COPY migrations ./migrations
# Editable, so the packages stay in /app beside migrations/ and web/: labelqueue finds its
# Alembic scripts at <repo>/migrations, next to the package, which a regular install into
# site-packages would leave behind.
RUN pip install --no-deps -e ".[postgres]" \
    && python -c "from labelqueue.db import MIGRATIONS_DIR; assert (MIGRATIONS_DIR / 'env.py').is_file(), MIGRATIONS_DIR" \
    && useradd --create-home --uid 1000 sepoa \
    && mkdir -p /data \
    && chown sepoa:sepoa /data

# A named volume mounted at /data takes this folder's owner, so the app need not run as root.
USER sepoa
ENV SEPOA_DATA_DIR=/data
VOLUME ["/data"]
EXPOSE 8000
ENTRYPOINT ["sepoa"]
CMD ["serve", "--host", "0.0.0.0", "--port", "8000"]
