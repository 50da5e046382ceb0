import os

# Off-screen rendering through EGL (a GPU's, or Mesa's on CPU), before anything imports MuJoCo.
os.environ.setdefault("MUJOCO_GL", "egl")
