FROM python:3.11-slim-bookworm
RUN apt-get update && apt-get install -y --no-install-recommends \
        libegl1 libegl-mesa0 libgl1-mesa-dri libosmesa6 libglfw3 \
    && rm -rf /var/lib/apt/lists/*
WORKDIR /app
COPY pyproject.toml README.md ./
COPY trainer ./trainer
COPY server ./server
RUN pip install --no-cache-dir -e .
ENV MUJOCO_GL=egl
ENTRYPOINT ["sepoa"]
