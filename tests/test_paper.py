"""The paper's settings and the cached book networks."""
import numpy as np
import pytest

import flnotes as fl


def test_settings_match_the_paper_systems():
    assert fl.paper.system("MSD").u_max[0] == fl.paper.MSD_SETTING["u_max"]
    assert fl.paper.system("Quad-1D").u_max[0] == fl.paper.QUAD_SETTING["u_max"]
    P = fl.paper.MSD_SETTING["P"]
    assert np.all(np.linalg.eigvalsh(P) > 0), "the CLF matrix P must be positive definite"
    with pytest.raises(ValueError, match="unknown system"):
        fl.paper.system("pendulum")


def test_paper_net_is_cached_and_identical(tmp_path, monkeypatch):
    monkeypatch.setenv("FLNOTES_CACHE", str(tmp_path))
    kw = dict(widths=(6, 6), n_per_axis=8, max_iter=200)
    net1, rep1 = fl.paper_net("MSD", **kw)
    net2, rep2 = fl.paper_net("MSD", **kw)
    assert len(list(tmp_path.glob("net-MSD-*.npz"))) == 1
    X = fl.msd().grid(5)
    assert np.array_equal(net1(X), net2(X))
    assert np.allclose(rep1.grid_max_error, rep2.grid_max_error)
    # the report's grid error is the true max error of the net on the training grid
    s = fl.msd()
    G = s.grid(8)
    assert np.isclose(np.abs(net1(G) - s.phi_stacked(G)).max(), rep1.grid_max_error[0])


def test_scale_switch(monkeypatch):
    assert fl.scale(10, 2) in (10, 2)
    assert fl.scale(10, 2) == (2 if fl.FAST else 10)
