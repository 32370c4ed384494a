"""Writing frames to an animated GIF with Pillow (no display, no ffmpeg), or to an MP4 with
imageio and imageio-ffmpeg (the ``video`` extra, which ships its own ffmpeg binary).
"""
from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from PIL import Image

__all__ = ["VIDEO_FORMATS", "mp4_available", "save_gif", "save_mp4", "save_video"]

VIDEO_FORMATS = ("gif", "mp4")
"""The formats `save_video` writes (mp4 needs imageio's ffmpeg plugin)."""


def _as_uint8_frame(frame, index: int) -> np.ndarray:
    array = frame.detach().cpu().numpy() if isinstance(frame, torch.Tensor) else np.asarray(frame)
    if array.ndim != 3 or array.shape[-1] != 3:
        raise ValueError(f"save_gif: frame {index} must be [H, W, 3] RGB, got shape {array.shape}")
    if array.dtype != np.uint8:
        raise TypeError(f"save_gif: frame {index} must be uint8, got {array.dtype}")
    return array


def _palette_image(array: np.ndarray) -> Image.Image:
    """An exact palette image when the frame has at most 256 colours, else a quantised one.

    Building the palette from the frame's own colours is exact and about 4x faster than the
    median cut Pillow applies to RGB frames (Pillow's fast octree is as fast but not exact).
    """
    packed = (array[..., 0].astype(np.uint32) << 16) | (array[..., 1].astype(np.uint32) << 8) | array[..., 2]
    colours, index = np.unique(packed.reshape(-1), return_inverse=True)
    if len(colours) > 256:
        return Image.fromarray(array).quantize(256, method=Image.Quantize.FASTOCTREE, dither=Image.Dither.NONE)
    height, width = array.shape[:2]
    image = Image.frombytes("P", (width, height), index.astype(np.uint8).tobytes())
    palette = np.stack([(colours >> 16) & 255, (colours >> 8) & 255, colours & 255], -1).astype(np.uint8)
    image.putpalette(palette.reshape(-1).tolist())
    return image


def save_gif(frames: Sequence, path: str | os.PathLike, fps: float = 25.0, loop: int = 0) -> Path:
    """Writes ``[H, W, 3]`` uint8 frames (numpy arrays or tensors) to an animated GIF.

    Args:
        frames: the frames, all of one shape.
        path: output file; missing parent folders are created.
        fps: frames per second. GIF stores delays in hundredths of a second, so the delay is
            ``round(100 / fps)`` centiseconds: exact for 10, 20, 25 or 50 fps, while 30 fps
            plays at 33.3 fps. Browsers slow delays under 2 cs down, so keep ``fps <= 50``.
        loop: how many times viewers repeat the animation; ``0`` forever.

    Each frame is reduced to its own 256-colour palette: lossless for frames of at most 256
    colours (one env's frame has a few dozen; a 16-env grid about 150-250), otherwise a few
    edge shades are merged. Consecutive identical frames are merged by Pillow into one frame
    shown for their summed delay: the duration is kept, but the decoded frame count can be
    smaller than ``len(frames)``.

    Returns:
        the path written.
    """
    if len(frames) == 0:
        raise ValueError("save_gif: no frames to write")
    if not fps > 0:
        raise ValueError(f"save_gif: fps must be positive, got {fps}")
    arrays = [_as_uint8_frame(f, i) for i, f in enumerate(frames)]
    for i, array in enumerate(arrays):
        if array.shape != arrays[0].shape:
            raise ValueError(f"save_gif: frame {i} has shape {array.shape}, frame 0 has {arrays[0].shape}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    images = [_palette_image(a) for a in arrays]
    delay_ms = 10 * max(1, round(100 / fps))
    images[0].save(path, format="GIF", save_all=True, append_images=images[1:], duration=delay_ms, loop=loop)
    return path


def mp4_available() -> bool:
    """Whether MP4 can be written (imageio and imageio-ffmpeg are installed)."""
    import importlib.util

    return all(importlib.util.find_spec(name) is not None for name in ("imageio", "imageio_ffmpeg"))


def save_mp4(frames: Sequence, path: str | os.PathLike, fps: float = 25.0) -> Path:
    """Writes ``[H, W, 3]`` uint8 frames to an H.264 MP4 (imageio + imageio-ffmpeg: the ``video``
    extra). Odd frame sizes are padded by one white pixel (H.264's 4:2:0 needs even sizes).

    Args:
        frames: the frames, ``[H, W, 3]`` uint8, all of one shape.
        path: the file to write (its folder is created if missing).
        fps: frames per second (positive).

    Returns:
        ``path``, as a ``Path``.
    """
    if not mp4_available():
        raise ImportError('save_mp4 needs imageio and imageio-ffmpeg: pip install "torchrl_diffenvs[video]"')
    import imageio

    if len(frames) == 0:
        raise ValueError("save_mp4: no frames to write")
    if not fps > 0:
        raise ValueError(f"save_mp4: fps must be positive, got {fps}")
    arrays = [_as_uint8_frame(f, i) for i, f in enumerate(frames)]
    height, width = arrays[0].shape[:2]
    pad = ((0, height % 2), (0, width % 2), (0, 0))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with imageio.get_writer(path, format="FFMPEG", mode="I", fps=fps, codec="libx264", macro_block_size=1,
                            pixelformat="yuv420p") as writer:
        for i, array in enumerate(arrays):
            if array.shape != arrays[0].shape:
                raise ValueError(f"save_mp4: frame {i} has shape {array.shape}, frame 0 has {arrays[0].shape}")
            writer.append_data(np.pad(array, pad, constant_values=255))
    return path


def save_video(frames: Sequence, path: str | os.PathLike, fps: float = 25.0) -> Path:
    """[`save_gif`][torchrl_diffenvs.rendering.save_gif] or [`save_mp4`][torchrl_diffenvs.rendering.save_mp4],
    by the suffix of ``path``.

    Args:
        frames: the frames, ``[H, W, 3]`` uint8, all of one shape.
        path: the file to write: ``.gif`` or ``.mp4``.
        fps: frames per second.

    Returns:
        The path written, as a ``Path``.
    """
    suffix = Path(path).suffix.lower()
    if suffix == ".mp4":
        return save_mp4(frames, path, fps)
    if suffix == ".gif":
        return save_gif(frames, path, fps)
    raise ValueError(f"save_video: unknown video format {suffix!r} of {str(path)!r}; valid: .gif, .mp4")
