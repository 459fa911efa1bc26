"""Dask worker plugins of :mod:`flnotes.parallel` (imported only when a Dask client is used)."""
from __future__ import annotations

from distributed.diagnostics.plugin import WorkerPlugin


class KeepFreedMemory(WorkerPlugin):
    """:func:`flnotes.config.keep_freed_memory` on every worker of the cluster, now and on each worker that joins."""

    name = "flnotes-keep-freed-memory"
    idempotent = True

    def setup(self, worker) -> None:
        from .config import keep_freed_memory

        keep_freed_memory()
