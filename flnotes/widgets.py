"""Interactive explorers (ipywidgets) used in the chapters.

Each explorer shows two things. First a kernel-free player: its frames are
drawn when the notebook is executed and embedded in the page, behind sliders
that run in the browser (:func:`flnotes.plots.static.frame_player`), so the
built book moves offline, without a kernel or a network. Then the ipywidgets
sliders, which recompute the figure in a running kernel, on release
(``continuous_update=False``). The explorers live beside the figures they
animate in :mod:`flnotes.plots` and are collected here, with their kernel-free
halves (``static_*``).
"""
from __future__ import annotations

from .plots import (static_feasible_set, explore_feasible_set, static_architecture, explore_architecture, explore_horizon,
    frame_player, FramePlayer)

__all__ = [
    'static_feasible_set', 'explore_feasible_set', 'static_architecture', 'explore_architecture',
    'explore_horizon', 'frame_player', 'FramePlayer'
]
