"""Frames without a display: a world-coordinate canvas, the drawer registry and ``env.render()``.

A *drawer* knows how to draw one task from one env's state (see [`register_drawer`][torchrl_diffenvs.rendering.register_drawer]);
[`render_frame`][torchrl_diffenvs.rendering.render_frame] picks the drawer of an env, reads the state of the requested envs from a
TensorDict (or from the env's latest output) and returns an RGB ``np.ndarray`` ``[H, W, 3]``,
uint8. Several envs are tiled into one grid frame.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Union

import numpy as np
import torch
from tensordict import TensorDictBase

try:
    from PIL import Image, ImageDraw, ImageFont
except ImportError as err:  # pragma: no cover - exercised only without the extra
    raise ImportError(
        "torchrl_diffenvs.rendering draws with Pillow, which is not installed: "
        'pip install "torchrl_diffenvs[render]"'
    ) from err

__all__ = [
    "Canvas", "Drawer", "register_drawer", "get_drawer", "list_drawers", "reward_color",
    "render_frame", "rollout_frames", "tile_frames",
]

RGB = tuple[int, int, int]
WHITE: RGB = (255, 255, 255)
#: Body colour of a frame that carries no reward (a freshly reset state) or a non-finite one.
NO_REWARD_COLOR: RGB = (150, 150, 165)
#: ``env_index="all"`` refuses grids larger than this (a 4096-env grid would need gigabytes).
MAX_GRID_ENVS = 256

Bounds = tuple[float, float, float, float]  # xmin, xmax, ymin, ymax in world units


def reward_color(unit_reward: float | None) -> RGB:
    """Ivy Gym's body colour ``RGB(1 - r, r, 0)``: red at reward 0, green at 1.

    Args:
        unit_reward: the reward mapped onto ``[0, 1]`` (clamped into it); ``None`` or a non-finite
            value gives `NO_REWARD_COLOR`.
    """
    if unit_reward is None or not math.isfinite(unit_reward):
        return NO_REWARD_COLOR
    r = min(max(unit_reward, 0.0), 1.0)
    return (round(255 * (1.0 - r)), round(255 * r), 0)


def transform(points, angle: float = 0.0, offset=(0.0, 0.0)) -> np.ndarray:
    """Rotates ``points`` counter-clockwise by ``angle``, then shifts them.

    Args:
        points: ``[K, 2]`` points (anything reshapeable to it).
        angle: the rotation (radians).
        offset: the shift ``(x, y)``, applied after the rotation.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    c, s = math.cos(angle), math.sin(angle)
    return p @ np.array([[c, s], [-s, c]]) + np.asarray(offset, dtype=np.float64)


class Canvas:
    """A Pillow image addressed in world coordinates (x right, y up).

    The world box ``bounds`` is fitted into ``size = (height, width)`` pixels with one scale for
    both axes (centred, so shapes are never stretched). Drawing happens at ``supersample`` times
    the resolution and is box-averaged down in [`to_array`][torchrl_diffenvs.rendering.Canvas.to_array], which smooths the edges that
    Pillow's ``ImageDraw`` leaves jagged. Shapes with non-finite coordinates are skipped and
    the frame gets a "non-finite state" label instead of an exception.
    """

    def __init__(self, size: tuple[int, int], bounds: Bounds, background: RGB = WHITE, supersample: int = 2):
        height, width = size
        xmin, xmax, ymin, ymax = (float(b) for b in bounds)
        if not (xmax > xmin and ymax > ymin):
            raise ValueError(f"Canvas bounds must satisfy xmin < xmax and ymin < ymax, got {bounds}")
        self.size = (height, width)
        self.supersample = ss = int(supersample)
        self.scale = min(width / (xmax - xmin), height / (ymax - ymin)) * ss  # pixels per world unit
        self._ox = width * ss / 2 - (xmin + xmax) / 2 * self.scale
        self._oy = height * ss / 2 + (ymin + ymax) / 2 * self.scale
        # far-away points are clamped so Pillow never sees coordinates it cannot rasterise
        self._limit = 8.0 * max(width, height) * ss
        self.image = Image.new("RGB", (width * ss, height * ss), background)
        self.draw = ImageDraw.Draw(self.image)
        self.non_finite = False

    @property
    def view(self) -> Bounds:
        """The world box actually visible (``bounds`` widened to the image's aspect ratio)."""
        height, width = self.size
        ss = self.supersample
        return (
            -self._ox / self.scale, (width * ss - self._ox) / self.scale,
            (self._oy - height * ss) / self.scale, self._oy / self.scale,
        )

    def pixels(self, points) -> list[tuple[float, float]] | None:
        """World points ``[K, 2]`` -> supersampled pixel coordinates; ``None`` if any is not finite."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        if not np.isfinite(p).all():
            self.non_finite = True
            return None
        x = np.clip(self._ox + p[:, 0] * self.scale, -self._limit, self._limit)
        y = np.clip(self._oy - p[:, 1] * self.scale, -self._limit, self._limit)
        return list(zip(x.tolist(), y.tolist()))

    def polygon(self, points, fill: RGB, outline: RGB | None = None) -> None:
        """Fills the polygon through ``points`` (``[k, 2]``, world metres); nothing where a point
        is not finite (the frame is flagged ``non_finite``)."""
        px = self.pixels(points)
        if px is not None:
            self.draw.polygon(px, fill=fill, outline=outline)

    def circle(self, center, radius: float, fill: RGB, outline: RGB | None = None) -> None:
        """Fills the circle of ``radius`` metres about ``center`` (``[2]`` or ``[1, 2]``, world
        metres); nothing where the centre or the radius is not finite."""
        px = self.pixels(center)
        if px is None or not math.isfinite(radius):
            return
        (x, y), r = px[0], abs(radius) * self.scale
        self.draw.ellipse([x - r, y - r, x + r, y + r], fill=fill, outline=outline)

    def line(self, points, fill: RGB, width: float = 1.0) -> None:
        """A polyline; ``width`` in pixels of the final image."""
        px = self.pixels(points)
        if px is not None:
            self.draw.line(px, fill=fill, width=max(1, round(width * self.supersample)), joint="curve")

    def to_array(self) -> np.ndarray:
        """The finished picture, ``[H, W, 3]`` uint8."""
        image = self.image.reduce(self.supersample) if self.supersample > 1 else self.image
        if self.non_finite:
            ImageDraw.Draw(image).text((4, 4), "non-finite state", fill=(200, 0, 0), font=_font())
        return np.asarray(image, dtype=np.uint8).copy()


@dataclass(frozen=True)
class Drawer:
    """How to draw one task.

    Attributes:
        draw: ``draw(canvas, state, params, color)`` draws one env; ``state`` and ``params`` map
            names to Python floats (scalars) or float64 ``np.ndarray`` (vectors) of that env;
            ``color`` is the reward colour of the main body.
        bounds: the world box ``(xmin, xmax, ymin, ymax)`` to show, or a function
            ``bounds(state, params)`` returning it.
        reward_range: rewards mapped linearly from this range onto ``[0, 1]`` for the colour.
        background: RGB background colour.
    """

    draw: Callable[[Canvas, Mapping[str, Any], Mapping[str, Any], RGB], None]
    bounds: Bounds | Callable[[Mapping[str, Any], Mapping[str, Any]], Bounds]
    reward_range: tuple[float, float] = (0.0, 1.0)
    background: RGB = WHITE

    def unit_reward(self, reward: float | None) -> float | None:
        """``reward`` scaled from ``reward_range`` to [0, 1] (for the reward bar), or ``None``."""
        if reward is None:
            return None
        low, high = self.reward_range
        return (reward - low) / (high - low)

    def picture(self, state, params, reward: float | None, size: tuple[int, int], supersample: int = 2) -> np.ndarray:
        """Draws one env: ``[H, W, 3]`` uint8."""
        bounds = self.bounds(state, params) if callable(self.bounds) else self.bounds
        canvas = Canvas(size, bounds, background=self.background, supersample=supersample)
        self.draw(canvas, state, params, reward_color(self.unit_reward(reward)))
        return canvas.to_array()


_DRAWERS: dict[str, Drawer] = {}


def register_drawer(
    name: str,
    draw: Callable | None = None,
    *,
    bounds: Bounds | Callable,
    reward_range: tuple[float, float] = (0.0, 1.0),
    background: RGB = WHITE,
    overwrite: bool = False,
):
    """Registers how to draw the task ``name`` (an env's ``name``); usable as a decorator.

    For example:

    ```python
    @register_drawer("mytask", bounds=(-2, 2, -2, 2))
    def draw_mytask(canvas, state, params, color):
        canvas.circle((state["x"], 0.0), 0.2, fill=color)
    ```

    Args:
        name: the task's name (an env's ``name``).
        draw: ``draw(canvas, state, params, color)``, which draws one env
            (see [`Drawer`][torchrl_diffenvs.rendering.Drawer]); ``None`` when used as
            ``@register_drawer(name, ...)``, which returns the decorator.
        bounds: the world box ``(xmin, xmax, ymin, ymax)`` to show, or a function
            ``bounds(state, params)`` returning it.
        reward_range: rewards mapped linearly from this range ``(low, high)``, ``low < high``, onto
            ``[0, 1]`` for the colour.
        background: RGB background colour.
        overwrite: replace a drawer already registered under ``name`` (else that is an error).

    Returns:
        ``draw``; without ``draw``, a decorator that registers the function it is given.
    """
    low, high = reward_range
    if not high > low:
        raise ValueError(f"register_drawer({name!r}): reward_range must be (low, high) with low < high, got {reward_range}")

    def add(fn: Callable) -> Callable:
        if name in _DRAWERS and not overwrite:
            raise ValueError(f"a drawer for {name!r} is already registered; pass overwrite=True to replace it")
        _DRAWERS[name] = Drawer(fn, bounds, (float(low), float(high)), background)
        return fn

    return add if draw is None else add(draw)


def list_drawers() -> list[str]:
    """The task names that have a drawer (registered tasks with one, and [`register_drawer`][torchrl_diffenvs.rendering.register_drawer]'s)."""
    from ..envs.registry import list_envs, task_spec

    return sorted(set(_DRAWERS) | {name for name in list_envs() if task_spec(name).drawer is not None})


def get_drawer(env_or_name) -> Drawer:
    """The drawer of an env or a task name: one added with
    [`register_drawer`][torchrl_diffenvs.rendering.register_drawer] (by the env's ``name``, then its base
    classes' names), else the one named in the task's registration.

    Args:
        env_or_name: an env, or a task name.
    """
    from ..envs.registry import list_envs, task_drawer

    if isinstance(env_or_name, str):
        names = [env_or_name]
    else:
        names = [getattr(env_or_name, "name", None)]
        names += [getattr(cls, "name", None) for cls in type(env_or_name).__mro__]
    names = [n for n in names if isinstance(n, str) and n]
    for name in names:
        if name in _DRAWERS:
            return _DRAWERS[name]
    for name in names:
        if name in list_envs():
            drawer = task_drawer(name)
            if drawer is not None:
                return drawer
    what = repr(env_or_name) if isinstance(env_or_name, str) else f"{names[0] if names else None!r} ({type(env_or_name).__name__})"
    raise KeyError(
        f"no drawer registered for env {what}; drawers exist for: {', '.join(list_drawers())}. "
        "Add one with torchrl_diffenvs.rendering.register_drawer(name, draw, bounds=...), or name one in the "
        "task's registration: @register_env(drawer='module:attribute')."
    )


# ---------------------------------------------------------------------------- reading envs out of TensorDicts
def _to_python(value: torch.Tensor):
    array = value.detach().to("cpu", torch.float64).numpy()
    return float(array) if array.ndim == 0 else array


def _snapshot(source, index: int, default_params: TensorDictBase):
    """``(state, params, reward)`` of env ``index``; ``source`` is a TensorDict, the env's latest
    output (a dict, see ``DiffEnv._remember_for_render``) or a partial-reset triple of those."""
    if isinstance(source, tuple):
        # (output before the reset, reset output, "_reset" mask): only masked envs were reset
        previous, fresh, mask = source
        return _snapshot(fresh if bool(mask.reshape(-1)[index]) else previous, index, default_params)
    state = {key: _to_python(value[index]) for key, value in source.get("state").items()}
    params_source = source.get("params", None)
    params_source = default_params if params_source is None else params_source
    params = {key: _to_python(value[index]) for key, value in params_source.items()}
    reward = source.get("reward", None)
    if reward is None and isinstance(source, TensorDictBase):  # a multi-agent step: ("agents", "reward")
        reward = source.get(("agents", "reward"), None)
    # one colour per env: the mean over its agents (a single-agent reward is one number)
    reward = None if reward is None else float(reward[index].detach().to(torch.float64).mean())
    return state, params, reward


def _check_source(env, tensordict) -> tuple[Any, int]:
    """Returns the TensorDict (or partial-reset triple) to draw and its number of envs."""
    if tensordict is None:
        source = getattr(env, "_render_source", None)
        if source is None:
            raise RuntimeError(f"{env.name}: nothing to render yet; call env.reset() or env.step() first, or pass a TensorDict")
        fresh = source[1] if isinstance(source, tuple) else source  # partial-reset triple: see _snapshot
        return source, fresh["num_envs"]
    if not isinstance(tensordict, TensorDictBase):
        raise TypeError(f"{env.name}: render expects a TensorDict or None, got {type(tensordict).__name__}")
    if "state" not in tensordict.keys():
        hint = " (its 'next' entry has one: pass td['next'])" if ("next", "state") in tensordict.keys(True) else ""
        raise KeyError(
            f"{env.name}: render needs a TensorDict with a 'state' entry, such as env.reset()'s output "
            f"or td['next'] of a step{hint}; got keys {sorted(map(str, tensordict.keys()))}"
        )
    if tensordict.batch_dims == 0:
        return tensordict.unsqueeze(0), 1
    if tensordict.batch_dims != 1:
        raise ValueError(
            f"{env.name}: render draws one time step of a [num_envs] TensorDict, got batch size "
            f"{tuple(tensordict.batch_size)}; for a [num_envs, T] rollout use rollout_frames(env, td) "
            "or pass td[:, t]['next']"
        )
    return tensordict, tensordict.batch_size[0]


def _indices(env_index, n: int, name: str) -> tuple[list[int], bool]:
    """Resolves ``env_index`` into a list of indices and whether a grid was asked for."""
    if isinstance(env_index, str):
        if env_index != "all":
            raise ValueError(f"{name}: env_index must be an int, a list of ints or 'all', got {env_index!r}")
        if n > MAX_GRID_ENVS:
            raise ValueError(
                f"{name}: env_index='all' would tile {n} envs (at most {MAX_GRID_ENVS}); pass a list of indices"
            )
        return list(range(n)), True
    grid = not isinstance(env_index, (int, np.integer))
    indices = [env_index] if not grid else list(env_index)
    if grid and not indices:
        raise ValueError(f"{name}: env_index is an empty list")
    if grid and len(indices) > MAX_GRID_ENVS:
        raise ValueError(f"{name}: at most {MAX_GRID_ENVS} envs per grid frame, got {len(indices)}")
    for i in indices:
        if isinstance(i, bool) or not isinstance(i, (int, np.integer)) or not -n <= i < n:
            raise IndexError(f"{name}: env_index {i!r} out of range for {n} envs (valid: 0..{n - 1}, or 'all')")
    return [int(i) % n for i in indices], grid


def _size(size) -> tuple[int, int]:
    if isinstance(size, (int, np.integer)) and not isinstance(size, bool):
        size = (size, size)
    try:
        height, width = (int(s) for s in size)
    except (TypeError, ValueError):
        raise ValueError(f"size must be an int or (height, width), got {size!r}") from None
    if height < 16 or width < 16:
        raise ValueError(f"size must be at least 16 pixels each way, got (height, width) = {(height, width)}")
    return height, width


def render_frame(
    env,
    tensordict: TensorDictBase | None = None,
    env_index: Union[int, Sequence[int], str] = 0,
    size: Union[int, tuple[int, int]] = 256,
    supersample: int = 2,
    ncols: int | None = None,
) -> np.ndarray:
    """Draws envs of ``env`` as one RGB frame ``[H, W, 3]`` uint8 (what ``env.render`` returns).

    Args:
        env: a [`DiffEnv`][torchrl_diffenvs.DiffEnv] whose task has a drawer.
        tensordict: a ``[N]`` (or unbatched) TensorDict with ``"state"``; ``"reward"`` colours
            the main body (without it, e.g. right after a reset, the body is grey) and
            ``"params"`` default to ``env.params``. Pass ``td["next"]`` of a step to draw the
            post-step state. ``None``: the env's latest ``step`` / ``reset`` output.
        env_index: one index (a ``size`` frame), or a list of indices / ``"all"`` (a grid of
            ``size`` cells, ``ncols`` columns, default ``ceil(sqrt(k))``, labelled with the index).
        size: pixels of one env's picture, ``int`` or ``(height, width)``.
        supersample: drawing resolution factor (2 smooths the edges; 1 is fastest).
    """
    name = getattr(env, "name", type(env).__name__)
    drawer = get_drawer(env)
    source, n = _check_source(env, tensordict)
    indices, grid = _indices(env_index, n, name)
    size = _size(size)
    pictures = [drawer.picture(*_snapshot(source, i, env.params), size, supersample) for i in indices]
    if not grid:
        return pictures[0]
    return tile_frames(pictures, ncols=ncols, labels=[str(i) for i in indices])


def rollout_frames(
    env,
    rollout: TensorDictBase,
    env_index: Union[int, Sequence[int], str] = 0,
    size: Union[int, tuple[int, int]] = 256,
    include_reset: bool = True,
    **kwargs,
) -> list[np.ndarray]:
    """Frames of a ``[N, T]`` rollout (``env.rollout`` output): the reset state, then every post-step state.

    Frame ``t + 1`` draws ``rollout[:, t]["next"]``, coloured by that step's reward.

    Args:
        env: the env that made the rollout (its task must have a drawer).
        rollout: a ``[N, T]`` rollout.
        env_index: which envs each frame draws, as in [`render_frame`][torchrl_diffenvs.rendering.render_frame]:
            one index, or a list of indices / ``"all"`` (a grid).
        size: pixels of one env's picture, ``int`` or ``(height, width)``.
        include_reset: a first frame drawing ``rollout[:, 0]`` (the reset state) in the no-reward grey.
        **kwargs: go to [`render_frame`][torchrl_diffenvs.rendering.render_frame] (``supersample``, ``ncols``).
    """
    if rollout.batch_dims != 2:
        raise ValueError(f"rollout_frames expects a [num_envs, T] rollout, got batch size {tuple(rollout.batch_size)}")
    frames = [render_frame(env, rollout[:, 0], env_index, size, **kwargs)] if include_reset else []
    nxt = rollout.get("next")
    for t in range(rollout.batch_size[1]):
        frames.append(render_frame(env, nxt[:, t], env_index, size, **kwargs))
    return frames


_FONT = None


def _font():
    global _FONT
    if _FONT is None:
        _FONT = ImageFont.load_default()  # bundled with Pillow; nothing is downloaded
    return _FONT


def tile_frames(
    frames: Sequence[np.ndarray], ncols: int | None = None, labels: Sequence[str] | None = None,
    border: RGB = (190, 190, 190),
) -> np.ndarray:
    """Tiles equal-sized ``[h, w, 3]`` frames row by row into ``[rows * h, cols * w, 3]``; empty
    cells are white.

    Args:
        frames: ``k`` uint8 frames of one shape ``[h, w, 3]``.
        ncols: the number of columns (default ``ceil(sqrt(k))``).
        labels: one label per frame, written small in the top-left corner of its cell.
        border: the colour of the 1-pixel border each cell gets inside its area.
    """
    if not len(frames):
        raise ValueError("tile_frames needs at least one frame")
    h, w = frames[0].shape[:2]
    for f in frames:
        if f.shape != (h, w, 3) or f.dtype != np.uint8:
            raise ValueError(f"tile_frames needs uint8 frames of one shape {(h, w, 3)}, got {f.shape} {f.dtype}")
    k = len(frames)
    ncols = ncols or math.ceil(math.sqrt(k))
    nrows = math.ceil(k / ncols)
    grid = Image.new("RGB", (ncols * w, nrows * h), WHITE)
    draw = ImageDraw.Draw(grid)
    for i, frame in enumerate(frames):
        row, col = divmod(i, ncols)
        x0, y0 = col * w, row * h
        grid.paste(Image.fromarray(frame), (x0, y0))
        draw.rectangle([x0, y0, x0 + w - 1, y0 + h - 1], outline=border)
        if labels is not None:
            draw.text((x0 + 4, y0 + 3), labels[i], fill=(60, 60, 60), font=_font())
    return np.asarray(grid, dtype=np.uint8).copy()
