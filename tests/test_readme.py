"""The README's example for a user's own system runs as printed and does what it claims."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

README = Path(__file__).resolve().parent.parent / "README.md"


def _example() -> str:
    text = README.read_text(encoding="utf-8")
    sec = text.split("## Use it on your own system", 1)
    assert len(sec) == 2, "README.md lost its section 'Use it on your own system'"
    blocks = re.findall(r"```python\n(.*?)```", sec[1].split("\n## ", 1)[0], re.S)
    assert len(blocks) == 1, "the section should hold exactly one python example"
    return blocks[0]


def test_readme_example_runs_and_keeps_the_bound(capsys):
    ns: dict = {}
    exec(compile(_example(), "README.md", "exec"), ns)  # noqa: S102 - our own README
    duff, net, eps = ns["duff"], ns["net"], ns["eps"]
    # the certified eps bounds the error at every sampled point of the box
    rng = np.random.default_rng(0)
    x = rng.uniform(duff.lo, duff.hi, size=(100_000, duff.n_in))
    err = np.abs(duff.phi_stacked(x) - net(x)).max(axis=0)
    assert np.all(err <= eps), (err, eps)
    # both closed loops on the true plant: |u| <= u_max at every sample, the CLF-CBF run converges
    for name in ("log", "log_mpc"):
        lg = ns[name]
        assert lg.n_steps > 0 and np.all(np.abs(lg.u) <= duff.u_max + 1e-9), name
        assert lg.fallback.sum() == 0, name
    assert ns["log"].summary()["final_norm_z"] < 0.1
    out = capsys.readouterr().out
    assert "MPC: |u| <= u_max at every sample: True" in out
