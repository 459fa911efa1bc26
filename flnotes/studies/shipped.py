"""``make reference``: retrain and recertify everything shipped in ``flnotes/data``, on one machine or a cluster.

``python -m flnotes.studies.shipped [--workers N | --scheduler ADDRESS] [--fresh] [part ...]`` writes, in
this order, the book's networks (:func:`flnotes.paper.write_references`), chapter 5's sweep
(:func:`flnotes.studies.write_sweep`), the two-link arm's network (:func:`flnotes.arm.make_arm_reference`),
the networks of the systems not in the book (:func:`flnotes.studies.unseen.write_unseen_references`) and
the networks of the time-versus-size study (:func:`flnotes.studies.size.write_size_references`, into ``size/``)
and the bound atlas of the MSD's network (:func:`flnotes.atlas.write_shipped_atlases`, after its network).
Each part spreads its networks (or, for the arm, its certification's boxes) over the workers; the files
are written by this process. A run that stops (a killed worker, a lost connection) is resumed from the
networks already finished (kept in the cache folder, :func:`flnotes.config.cache_dir`); ``--fresh`` starts
over. Only to change the book's networks on purpose: commit the result.
"""
from __future__ import annotations

import sys
from pathlib import Path
from typing import Optional, Sequence

PARTS = ("references", "sweep", "arm", "unseen", "size", "atlas")


def write_all(parts: Sequence[str] = PARTS, workers: Optional[int] = None, client=None, resume: bool = True,
              progress: bool = True, folder=None) -> list[str]:
    """Write the shipped files of ``parts`` (see the module's docstring); returns what was written."""
    from .. import paper
    from ..arm import make_arm_reference
    from ..parallel import using
    from .networks import write_sweep
    from .size import write_size_references
    from .unseen import write_unseen_references

    bad = [p for p in parts if p not in PARTS]
    if bad:
        raise ValueError(f"unknown part(s) {bad}; choose from {list(PARTS)}")
    out: list[str] = []
    with using(workers, client) as ex:
        if "references" in parts:
            out += paper.write_references(folder=folder, client=ex, progress=progress, resume=resume)
        if "sweep" in parts:
            write_sweep(folder=folder, client=ex, progress=progress, resume=resume)
            out.append("sweep-MSD.table.json")
        if "arm" in parts:
            out.append(str(make_arm_reference(folder=folder, client=ex, progress=progress)))
        if "unseen" in parts:
            out += write_unseen_references(folder=folder, client=ex, progress=progress, resume=resume)
        if "size" in parts:
            out += write_size_references(folder=None if folder is None else Path(folder) / "size", client=ex,
                                         progress=progress, resume=resume)
        if "atlas" in parts:
            from ..atlas import write_shipped_atlases

            out += write_shipped_atlases(folder=folder)
    return out


def main(argv: Optional[list[str]] = None) -> int:
    """The command line of ``make reference`` (see the module's docstring)."""
    from ..parallel import parse_workers

    usage = (f"usage: python -m flnotes.studies.shipped [--workers N | --scheduler ADDRESS] [--fresh] "
             f"[{' | '.join(PARTS)} ...]")
    argv = sys.argv[1:] if argv is None else argv
    try:
        workers, scheduler, rest = parse_workers(argv)
        bad = [a for a in rest if a not in PARTS and a != "--fresh"]
        if bad:
            raise ValueError(f"unknown argument(s) {bad}")
    except ValueError as exc:
        print(f"{exc}. {usage}", file=sys.stderr)
        return 2
    parts = [a for a in rest if a in PARTS] or list(PARTS)
    for path in write_all(parts, workers=workers, client=scheduler, resume="--fresh" not in rest):
        print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
