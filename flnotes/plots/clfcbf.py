"""Figures of the book: clfcbf part."""
from __future__ import annotations

__all__: list[str] = []
