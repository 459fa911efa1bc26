"""Explorers that work without a kernel: precomputed frames behind sliders that run in the browser.

The ipywidgets explorers of :mod:`flnotes.widgets` recompute their figure in the
kernel, so a static HTML page (the built book, read offline) cannot move them.
:func:`frame_player` draws every combination of the slider values once, when the
notebook is executed, encodes the figures as PNG data URIs and returns a small,
self-contained HTML/JavaScript player: one ``<input type="range">`` per slider
and an ``<img>`` whose source is swapped in the browser. No kernel, no network,
no external script.

The player also reads the page address: ``#<player id>=i,j,...`` (indices into
the slider values) moves the sliders there on load, through the same handler a
reader triggers, so a headless browser can check that the picture moves.
"""
from __future__ import annotations

import base64
import html
import io
import itertools
import json
import re
from typing import Callable, Mapping, Sequence

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.figure import Figure

from .._checks import brief, check_int, check_number

__all__ = ["FramePlayer", "frame_player"]


def _slider_values(values, name: str) -> list:
    """A slider's values as a list: a non-empty ordered collection (a list, tuple, range, 1-d array, pandas Series, a
    dict's keys, a generator), else ``ValueError`` naming ``name`` (a string, a mapping, a set, which has no order, or
    a single value)."""
    unordered = isinstance(values, (str, bytes, Mapping, set, frozenset)) or (isinstance(values, np.ndarray)
                                                                              and values.ndim != 1)
    try:
        out = None if unordered else list(values)
    except TypeError:  # not iterable: a single value
        out = None
    if not out:
        raise ValueError(f"{name} must be a non-empty ordered collection of values (a list, tuple, range or 1-d array) "
                         f"for the slider to step through, got {brief(values)}")
    return out


def _start(start, axes: list, labels: list) -> list:
    """``start`` as one index per slider (integers, 0-based, each within its slider's values), else ``ValueError``."""
    if not (isinstance(start, (list, tuple, range)) or (isinstance(start, np.ndarray) and start.ndim == 1)):
        raise ValueError(f"start must be a list of {len(axes)} indices, one per slider (0-based), got {brief(start)}")
    if len(start) != len(axes):
        raise ValueError(f"start must hold one index per slider ({len(axes)}: {labels}), got {len(start)}: "
                         f"{brief(start)}")
    out = []
    for d, (s, v) in enumerate(zip(start, axes)):
        if isinstance(s, (float, np.floating)) and np.isfinite(s) and float(s).is_integer():
            s = int(s)  # an integral float (1.0) is that index; 1.7 is none
        i = check_int(s, f"start[{d}]", 0, f"the index, 0-based, of the first value of slider {labels[d]!r}")
        if i >= len(v):
            raise ValueError(f"start[{d}] must index the values of slider {labels[d]!r}: 0..{len(v) - 1}, got {i}")
        out.append(i)
    return out


def _png_data_uri(fig, dpi: float) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


class FramePlayer:
    """Precomputed frames and their sliders; displays as self-contained HTML (``_repr_html_``).

    Attributes
    ----------
    name
        Identifier of the player in the page (``id`` of its ``<div>``).
    sliders
        ``{label: values}`` in slider order.
    frames
        ``{"i,j,...": data URI}``, one PNG per combination of slider indices.
    start
        Indices shown first.
    """

    def __init__(self, name: str, sliders: Mapping[str, Sequence], frames: Mapping[str, str], start: Sequence[int]):
        self.name, self.sliders, self.frames, self.start = name, dict(sliders), dict(frames), list(start)

    def __len__(self) -> int:
        return len(self.frames)

    def __repr__(self) -> str:
        dims = " x ".join(f"{k} ({len(v)})" for k, v in self.sliders.items())
        return f"FramePlayer({self.name!r}: {len(self)} precomputed frames over {dims})"

    def _repr_html_(self) -> str:
        pid = self.name
        labels = [html.escape(str(k)) for k in self.sliders]
        values = [[str(v) for v in vals] for vals in self.sliders.values()]
        key0 = ",".join(map(str, self.start))
        rows = "".join(
            f'<label style="display:inline-block;margin-right:1.2em">{lab} '
            f'<input type="range" class="fl-slider" data-dim="{d}" min="0" max="{len(vals) - 1}" step="1" '
            f'value="{self.start[d]}" aria-label="{lab}"> '
            f'<output class="fl-value">{html.escape(vals[self.start[d]])}</output></label>'
            for d, (lab, vals) in enumerate(zip(labels, values)))
        script = (
            "(function(){"
            f"var root=document.getElementById({json.dumps(pid)});"
            f"var frames={json.dumps(self.frames)};var values={json.dumps(values)};"
            "var sl=root.querySelectorAll('input.fl-slider');var out=root.querySelectorAll('output.fl-value');"
            "var img=root.querySelector('img.fl-frame');"
            "function show(){var k=[];for(var d=0;d<sl.length;d++){k.push(sl[d].value);"
            "out[d].textContent=values[d][sl[d].value];}"
            "var key=k.join(',');img.src=frames[key];img.setAttribute('data-frame',key);}"
            "for(var d=0;d<sl.length;d++){sl[d].addEventListener('input',show);}"
            "var m=new RegExp('[#&]'+root.id+'=([0-9,]+)').exec(window.location.hash);"
            "if(m){var idx=m[1].split(',');for(var d=0;d<sl.length&&d<idx.length;d++){sl[d].value=idx[d];"
            "sl[d].dispatchEvent(new Event('input'));}}"
            "})();")
        return (f'<div class="fl-static-explorer" id="{pid}" style="margin:0.5em 0">'
                f'<div style="font-size:0.9em">{rows}</div>'
                f'<img class="fl-frame" data-frame="{key0}" alt="explorer frame" style="max-width:100%" '
                f'src="{self.frames[key0]}"><script>{script}</script></div>')


def frame_player(draw: Callable[..., object], sliders: Mapping[str, Sequence], name: str,
                 start: Sequence[int] | None = None, dpi: float = 60) -> FramePlayer:
    """Draw ``draw(*values)`` for every combination of the slider values; return the browser-side player.

    Parameters
    ----------
    draw
        Called with one value per slider (in the order of ``sliders``); returns
        a matplotlib figure (closed after encoding); anything else is a ``TypeError`` naming ``draw``.
    sliders
        ``{label: sequence of values}`` (a dict; each a non-empty list, tuple, range or 1-d array); each slider
        steps through its values.
    name
        Identifier of the player in the page: letters, digits, ``-`` and ``_``,
        starting with a letter; unique within a page.
    start
        Index of the first frame along each slider (default: the middle): one integer per slider, 0-based,
        within its values (``ValueError`` naming the entry otherwise: ``1.7``, ``True`` or ``"2"`` are no index).
    dpi
        Resolution of the PNG frames (dots per inch, a finite number >= 1, e.g. 60 or 72.5); keep it low, every frame
        is embedded.

    Returns
    -------
    FramePlayer
        Displayed as HTML by Jupyter and by the built book.
    """
    if not callable(draw):
        raise TypeError(f"draw must be a function of one value per slider returning a matplotlib figure, got "
                        f"{brief(draw)}")
    if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z][A-Za-z0-9_-]*", name):
        raise ValueError(f"name must start with a letter and hold only letters, digits, '-' and '_', got {name!r}")
    if not isinstance(sliders, Mapping):
        raise TypeError(f"sliders must be a dict {{label: sequence of values}}, got {brief(sliders)}")
    if not sliders:
        raise ValueError("sliders must hold at least one {label: values} entry")
    dpi = check_number(dpi, "dpi", "dots per inch of the frames; below 1 a frame has hardly a pixel", low=1.0)
    axes = [_slider_values(v, f"sliders[{k!r}]") for k, v in sliders.items()]
    n_frames = 1
    for v in axes:
        n_frames *= len(v)
    if n_frames > 200:
        raise ValueError(f"{n_frames} frames would make the page heavy: use fewer slider values (at most 200 frames)")
    start = [len(v) // 2 for v in axes] if start is None else _start(start, axes, list(sliders))
    frames = {}
    for idx in itertools.product(*[range(len(v)) for v in axes]):
        fig = draw(*[v[i] for v, i in zip(axes, idx)])
        if not isinstance(fig, Figure):
            raise TypeError(f"draw must return a matplotlib figure (e.g. fig, ax = plt.subplots(); ...; return fig), "
                            f"got {brief(fig)} for the values {[v[i] for v, i in zip(axes, idx)]!r}")
        frames[",".join(map(str, idx))] = _png_data_uri(fig, dpi)
    return FramePlayer(name, dict(zip(sliders, axes)), frames, start)
