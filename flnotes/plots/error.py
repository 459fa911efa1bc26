"""Figures of the book: error part."""
from __future__ import annotations

__all__: list[str] = []
