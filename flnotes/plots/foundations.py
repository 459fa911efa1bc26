"""Figures of the book: foundations part."""
from __future__ import annotations

__all__: list[str] = []
