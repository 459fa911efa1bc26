"""Small networks the tests rely on, stored with the tests (trained once, the same on every machine).

They were written by :func:`flnotes.reference.save_reference` with ``folder=tests/data``; the JSON file
beside each ``.npz`` records the :func:`flnotes.fit_relu` settings that produced it.
"""
from pathlib import Path

from flnotes.reference import load_reference

DATA = Path(__file__).resolve().parent / "data"


def test_net(name: str):
    """The stored network ``name`` (checksum verified) and its training report."""
    ref = load_reference(name, folder=DATA)
    return ref.net, ref.report


test_net.__test__ = False  # a helper, not a test
