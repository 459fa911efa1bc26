"""Figures of the book: mpc part."""
from __future__ import annotations

__all__: list[str] = []
