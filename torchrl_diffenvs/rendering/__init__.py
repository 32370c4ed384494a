"""Rendering without a display: RGB frames of every task, grids of envs, GIF export.

``env.render(td=None, env_index=0 | [i, ...] | "all", size=256)`` returns an ``np.ndarray``
``[H, W, 3]`` uint8 drawn with Pillow; [`save_gif`][torchrl_diffenvs.rendering.save_gif] writes a list of frames. A task names its
drawer in its registration (``@register_env(drawer="module:attribute")``, imported on first use);
[`register_drawer`][torchrl_diffenvs.rendering.register_drawer] adds or overrides one by name. Needs the ``render`` extra (Pillow).
"""
from .core import (
    Canvas,
    Drawer,
    get_drawer,
    list_drawers,
    register_drawer,
    render_frame,
    reward_color,
    rollout_frames,
    tile_frames,
    transform,
)
from .video import VIDEO_FORMATS, mp4_available, save_gif, save_mp4, save_video

__all__ = [
    "Canvas", "Drawer", "get_drawer", "list_drawers", "register_drawer", "render_frame", "reward_color",
    "rollout_frames", "save_gif", "save_mp4", "save_video", "tile_frames", "transform", "VIDEO_FORMATS",
    "mp4_available",
]
