"""Clip files: the one h264 encoder of the app's clips, and the check of a clip a client uploads.

Both run imageio-ffmpeg's bundled ffmpeg (imported when first needed, so the server starts
fast). `encode_mp4` is what the worker's clips (`trainer.clips`) and an external client's frame
arrays (`server.routes.external`) are written with: libx264, yuv420p, the moov atom first so that a
browser plays the file before it has all of it. `probe_clip` decodes an uploaded file whole
with the same ffmpeg and says what it holds, or why it will not play on the label page.
"""

from __future__ import annotations

import os
import uuid
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from labelqueue.errors import Invalid
from runvocab.clip_format import ClipInfo

PLAYABLE = {"mp4": ("h264",), "webm": ("vp8", "vp9", "av1")}
"""the codecs the label page's browsers decode in each container"""
PLAYABLE_PIXELS = ("yuv420p", "yuvj420p")
"""the h264 pixel formats every browser decodes (a 4:4:4 h264 stream does not play)"""


def encode_mp4(frames: Iterable[np.ndarray], path: str | os.PathLike[str], *, fps: float,
               width: int, height: int, crf: int = 23, preset: str = "veryfast",
               pixel_format: str = "yuv420p", macro_block_size: int = 2) -> Path:
    """Writes the frames (uint8 (height, width, 3) each, an array or any iterable: frames are
    encoded as they come) to an h264 mp4 at `path`, atomically. Returns the path. ValueError
    for a frame of another shape or type, or no frames."""
    import imageio.v2 as imageio

    path = Path(path)
    if path.suffix != ".mp4":
        raise ValueError(f"clip path must end in .mp4, got {str(path)!r}")
    # Same folder (so the rename is atomic), hidden, and still .mp4 for ffmpeg's muxer choice.
    tmp = path.with_name(f".{path.stem}.{uuid.uuid4().hex[:12]}.tmp.mp4")
    writer = imageio.get_writer(
        tmp, format="FFMPEG", fps=fps, codec="libx264", pixelformat=pixel_format,
        macro_block_size=macro_block_size, quality=None,  # None: rate control from -crf
        ffmpeg_params=["-crf", str(crf), "-preset", preset, "-movflags", "+faststart",
                       # One encoder thread: the renderer has the other cores, and a clip of a
                       # few dozen frames gains nothing from x264's frame threads.
                       "-threads", "1"],
    )
    n = 0
    try:
        with writer:
            for frame in frames:
                if frame.shape != (height, width, 3) or frame.dtype != np.uint8:
                    raise ValueError(f"frame {n}: expected uint8 {(height, width, 3)}, "
                                     f"got {frame.dtype} {frame.shape}")
                writer.append_data(frame)
                n += 1
            if n == 0:
                raise ValueError("no frames to encode")
        with open(tmp, "rb") as f:  # on disk before it has its name, even after a crash
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def container_of(head: bytes) -> str | None:
    """mp4 or webm from a file's first bytes (an ISO BMFF `ftyp` box, an EBML header)."""
    if head[4:8] == b"ftyp":
        return "mp4"
    if head[:4] == b"\x1a\x45\xdf\xa3":
        return "webm"
    return None


def probe_clip(path: Path) -> ClipInfo:
    """Decode the clip at `path` whole and say what it holds; Invalid naming the problem for
    a file that is no MP4 or WebM, does not decode, or holds a codec or pixel format browsers
    do not play."""
    import imageio_ffmpeg  # type: ignore[import-untyped]

    with open(path, "rb") as f:
        container = container_of(f.read(16))
    if container is None:
        raise Invalid("the clip is neither an MP4 nor a WebM file")
    try:
        reader = imageio_ffmpeg.read_frames(str(path))
        meta = next(reader)
        reader.close()
        frames, seconds = imageio_ffmpeg.count_frames_and_secs(str(path))
    except (OSError, RuntimeError, StopIteration):
        raise Invalid(f"the clip does not decode as {container.upper()} video") from None
    codec = str(meta.get("codec", "")).split(",")[0].split()[0] if meta.get("codec") else ""
    pixels = str(meta.get("pix_fmt", "")).split("(")[0].strip()
    if codec not in PLAYABLE[container]:
        raise Invalid(f"the clip's codec is {codec or 'unknown'}; a {container.upper()} clip "
                         f"must be {' or '.join(PLAYABLE[container])} to play in a browser")
    if codec == "h264" and pixels not in PLAYABLE_PIXELS:
        raise Invalid(f"the clip's pixel format is {pixels}; an h264 clip must be yuv420p to "
                         "play in a browser")
    width, height = (int(v) for v in meta["size"])
    if frames < 1:
        raise Invalid("the clip holds no frames")
    return ClipInfo(container=container, codec=codec, width=width, height=height,
                    frames=int(frames), seconds=float(seconds))
