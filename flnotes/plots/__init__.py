"""The book's figures: each function turns a system, a network or a run log into one figure.

Submodules hold the figures of one part of the book each; everything is
re-exported here so a notebook writes ``fl.plots.phase_portrait(...)``.
"""
from .style import COLORS, new_axes, bound_lines, use_book_style

from .foundations import *  # noqa: F401,F403
from .error import *  # noqa: F401,F403
from .clfcbf import *  # noqa: F401,F403
from .mpc import *  # noqa: F401,F403
from .realtime import *  # noqa: F401,F403
from .static import FramePlayer, frame_player
