"""Interactive explorers (ipywidgets) used in the chapters.

Each explorer draws a static default figure first, so the rendered HTML book
shows something meaningful, and updates on release of a slider
(``continuous_update=False``). They live beside the figures they animate in
:mod:`flnotes.plots` and are collected here.
"""
from __future__ import annotations

from .plots import *  # noqa: F401,F403  (explore_* functions are defined in the plots submodules)

__all__ = [name for name in dir() if name.startswith("explore_")]
