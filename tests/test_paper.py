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


# --------------------------------------------------------------------------- shipped reference networks
@pytest.mark.parametrize("name", sorted(fl.paper.REFERENCES))
def test_shipped_reference_is_consistent(name):
    """Each shipped network loads with its checksum, and its stored report and bracket describe it."""
    ref = fl.reference.load_reference(name)
    sys_name, settings = fl.paper.REFERENCES[name]
    s = fl.paper.system(sys_name)
    assert ref.net.n_in == s.n_z + s.m and ref.net.widths == tuple(settings["widths"])
    # the report's grid error is the network's max error on the training grid
    G = fl.uniform_grid(s.lo, s.hi, ref.report.n_per_axis)
    assert np.isclose(np.abs(ref.net(G) - s.phi_stacked(G)).max(), ref.report.grid_max_error[0], rtol=1e-9)
    # the certified bracket contains every sampled error
    br = ref.bracket
    assert br["lower"][0] <= br["upper"][0]
    X = np.random.default_rng(0).uniform(s.lo, s.hi, (50_000, s.n_z + s.m))
    assert np.abs(ref.net(X) - s.phi_stacked(X)).max() <= br["upper"][0]
    assert np.abs(ref.net(np.array(br["argmax"])) - s.phi_stacked(np.array(br["argmax"]))).max() >= br["lower"][0] * (1 - 1e-9)


def test_paper_net_loads_the_shipped_network_and_refresh_trains(tmp_path, monkeypatch):
    monkeypatch.setenv("FLNOTES_CACHE", str(tmp_path))
    net, rep = fl.paper_net("Quad-1D")
    ref = fl.reference.load_reference("Quad-1D")
    assert fl.reference.weights_sha256(net) == ref.meta["sha256"]
    assert np.array_equal(fl.paper.paper_eps("Quad-1D").upper, ref.bracket["upper"])
    assert not list(tmp_path.iterdir()), "loading the shipped network must not train or write anything"
    # settings that match another shipped reference load it; others train (see the cached test above)
    n30, _ = fl.paper_net("MSD", n_per_axis=30, seed=0)
    assert fl.reference.weights_sha256(n30) == fl.reference.load_reference("MSD-n30").meta["sha256"]


def test_damaged_reference_is_refused(tmp_path):
    s = fl.quad1d()
    net, rep = fl.fit_relu(s.phi_stacked, s.lo, s.hi, widths=(3,), n_per_axis=4, max_iter=20)
    fl.reference.save_reference("tiny", net, rep, dict(widths=(3,)), folder=tmp_path)
    assert fl.reference.reference_names(tmp_path) == ["tiny"]
    back = fl.reference.load_reference("tiny", folder=tmp_path)
    assert np.array_equal(back.net(s.grid(3)), net(s.grid(3)))
    W = [w.copy() for w in net.W]
    W[0][0, 0] += 1e-12
    fl.ReLUNet(W, net.b).save(tmp_path / "tiny.npz")
    with pytest.raises(ValueError, match="checksum"):
        fl.reference.load_reference("tiny", folder=tmp_path)
    with pytest.raises(FileNotFoundError, match="shipped references"):
        fl.reference.load_reference("nope", folder=tmp_path)


def test_shipped_sweep_table_and_a_small_recomputed_sweep(tmp_path, monkeypatch):
    """Chapter 5's shipped sweep covers its grid and each row's certified eps bounds its sampled errors;
    the same code recomputes a small sweep on this machine."""
    rows = fl.studies.book_sweep("MSD")
    st = fl.paper.SWEEP_SETTINGS
    assert len(rows) == len(st["widths"]) * len(st["depths"]) * len(st["n_per_axis"])
    for r in rows:
        assert r["eps_lower"] <= r["eps_certified"] and max(r["eps_sample"], r["eps_pso"]) <= r["eps_certified"] + 1e-12
    monkeypatch.setenv("FLNOTES_CACHE", str(tmp_path))
    small = fl.studies.architecture_sweep(fl.msd(), widths=(4,), depths=(1,), n_per_axis=(6,), max_iter=30,
                                        n_samples=2000, max_time=5.0)
    (r,) = small
    assert r["width"] == 4 and r["eps_lower"] <= r["eps_certified"] and r["eps_sample"] <= r["eps_certified"] + 1e-12


def test_fit_relu_threads_are_validated():
    s = fl.quad1d()
    with pytest.raises(ValueError, match="threads"):
        fl.fit_relu(s.phi_stacked, s.lo, s.hi, widths=(3,), n_per_axis=3, threads=0)


def test_table1_flags_a_pso_estimate_below_the_certified_lower_bound():
    """Table 1 (chapter 5): a PSO value below the certified lower bound is marked invalid, next to the bracket."""
    rows = fl.studies.table1_rows(("Quad-1D",))
    paper_row, book_row = rows
    assert paper_row["PSO vs bracket"] == ""  # the paper's networks are not available: nothing certified
    lower = float(book_row["eps certified"].strip("[]").split(",")[0])
    assert book_row["eps (PSO)"] < lower, "premise: PSO with seed 0 misses the shipped Quad-1D network's maximum (ch. 5)"
    assert book_row["PSO vs bracket"] == "below: invalid"
