"""The study of networks cheaper to encode: shipped variants, their certified eps, the MPC's work with each."""
import numpy as np
import pytest

import flnotes as fl
from flnotes.studies import cheap_networks as study


@pytest.mark.parametrize("label", list(study.VARIANTS))
def test_each_variant_is_shipped_with_its_settings_and_a_certified_eps(label):
    net, eps = study.variant_network(label)
    settings = {**fl.paper.NET_SETTINGS["Quad-1D"], **study.VARIANTS[label]}
    assert net.widths == tuple(settings["widths"])
    s = fl.paper.system("Quad-1D")
    X = np.random.default_rng(1).uniform(s.lo, s.hi, (100_000, s.n_z + s.m))
    assert np.abs(net(X) - s.phi_stacked(X)).max() <= eps
    assert 0.0 < eps < s.u_max[0], "premise: u_max^eps = u_max - eps must be positive"


def test_rows_count_the_work_and_keep_the_true_input_bounded():
    labels = ["book (10, 10, 10)", "(16, 16)"]
    rows = study.network_rows(t_final=1.5, labels=labels)
    assert [r["network"] for r in rows] == labels
    for r in rows:
        net, _ = study.variant_network(r["network"])
        assert r["hidden"] == net.n_hidden and 0 <= r["unstable on box"] <= net.n_hidden
        assert r["steps"] == 15 and 0 <= r["screened"] <= r["steps"]
        # free binaries of one step's program: at most the unstable neurons of every encoded step
        assert r["binaries max"] <= 10 * r["unstable on box"]
        assert r["max |u|/u_max"] <= 1.0
        assert r["median ms"] <= r["max ms"]


def test_unknown_variant_is_named():
    with pytest.raises(ValueError, match="unknown variant"):
        study.variant_network("(3, 3)")
