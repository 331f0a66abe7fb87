"""What ``gym.make`` calls for every JEPA/* id: checks the arguments every env shares, then builds the env.

The ids are registered with ``creator(entry_point)`` rather than the class itself so that gymnasium does not
wrap a ``render_mode="human"`` request in its pygame window (``HumanRendering``), which fails deep inside
gymnasium when pygame is absent; these envs render offscreen, and the request is refused here, at ``gym.make``,
with the modes that work.
"""
from __future__ import annotations

import functools
import importlib

RENDER_MODES = (None, "rgb_array")


def _load(entry_point: str):
    module, _, name = entry_point.partition(":")
    return getattr(importlib.import_module(module), name)


def create(entry_point: str, **kwargs):
    mode = kwargs.get("render_mode")
    if mode not in RENDER_MODES:
        raise ValueError(
            f"render_mode={mode!r} is not supported: JEPA envs render offscreen (headless MuJoCo or a raster), so "
            f"use render_mode='rgb_array' and show the frames env.render() returns yourself (e.g. with "
            f"matplotlib or imageio), or render_mode=None; the camera images are in every observation anyway")
    return _load(entry_point)(**kwargs)


def creator(entry_point: str):
    """The callable to register for ``entry_point`` ("module:Class"); it imports the backend only when called."""
    return functools.partial(create, entry_point)
