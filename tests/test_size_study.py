"""The time-versus-size study: shipped networks with certified eps, their premise checked, the bench section."""
import json
import shutil

import numpy as np
import pytest

import flnotes as fl
from flnotes.tables import Table
from flnotes.studies import size as study

PAIRS = [(s, w) for s in study.SYSTEMS for w in study.SIZES[s]]


@pytest.mark.parametrize("system,widths", PAIRS, ids=[f"{s}-{study.size_label(w)}" for s, w in PAIRS])
def test_each_network_is_shipped_and_its_bracket_holds_on_fresh_samples(system, widths):
    net, eps, br = study.size_net(system, widths)
    assert net.widths == tuple(widths)
    s = fl.paper.system(system)
    assert 0.0 < eps < s.u_max[0], "premise: u_max^eps = u_max - eps must leave an input"
    assert float(np.max(br["lower"])) <= eps
    X = np.random.default_rng(12345).uniform(s.lo, s.hi, (50_000, s.n_in))     # not the certification's samples
    assert np.abs(net(X) - s.phi_stacked(X)).max() <= eps


def test_the_book_networks_are_the_study_points_of_their_size():
    assert study.size_reference_name("MSD", (20, 20, 20)) == ("MSD", None)
    assert study.size_reference_name("Quad-1D", (10, 10, 10)) == ("Quad-1D", None)
    assert study.size_reference_name("MSD", (30, 30))[0] == "size_MSD-30x2"


def test_a_file_that_breaks_the_premise_is_refused(tmp_path):
    name, where = study.size_reference_name("Quad-1D", (10, 10))
    for ext in ("npz", "json"):
        shutil.copy(where / f"{name}.{ext}", tmp_path / f"{name}.{ext}")
    study.size_net("Quad-1D", (10, 10), folder=tmp_path)                     # the copy loads
    meta = json.loads((tmp_path / f"{name}.json").read_text())
    meta["settings"]["seed"] = 99
    (tmp_path / f"{name}.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="study's settings"):
        study.size_net("Quad-1D", (10, 10), folder=tmp_path)
    meta["settings"]["seed"] = fl.paper.NET_SETTINGS["Quad-1D"]["seed"]
    meta["sha256"] = "0" * 64
    (tmp_path / f"{name}.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="checksum"):
        study.size_net("Quad-1D", (10, 10), folder=tmp_path)


def test_unknown_sizes_and_systems_are_named():
    with pytest.raises(ValueError, match="not in the study"):
        study.size_net("MSD", (7, 7))
    with pytest.raises(ValueError, match="unknown system"):
        study.size_net("Arm2", (10, 10))


def test_fast_bench_section_produces_the_table(tmp_path, monkeypatch):
    from flnotes.bench import size as section

    monkeypatch.setenv("FLNOTES_BENCH_DIR", str(tmp_path))
    sec = section.run(fast=True)
    args = section.settings(True)
    rows = sec["rows"]
    assert len(rows) == len(args["systems"]) * len(args["sizes"]) * len(args["horizons"])
    cols = {"system", "network", "hidden", "eps", "N_p", "binaries (box)", "binaries max", "optimal", "limit",
            "median ms", "p99 ms", "max ms", "cpu median ms", "cpu p90 ms", "cpu p99 ms", "cpu max ms", "over t_s",
            "cpu over t_s"}
    assert cols <= set(rows[0])
    assert any("within t_s of CPU time" in n and "90th percentile" in n for n in sec["notes"])
    steps = args["n_loops"] * args["loop_steps"] + args["n_cold"]
    for r in rows:
        assert r["steps"] == steps and r["optimal"] + r["limit"] + r["other"] == steps
        assert 0 <= r["limit, cpu < cap/2"] <= r["limit"]
        assert r["median ms"] <= r["p99 ms"] <= r["max ms"]
        assert r["cpu median ms"] <= r["cpu p90 ms"] <= r["cpu p99 ms"] <= r["cpu max ms"]
        assert r["cpu over t_s"] == 0 or r["cpu max ms"] > study.TS * 1e3
        assert r["binaries max"] <= r["binaries (box)"]
        widths = next(w for w in study.SIZES[r["system"]] if study.size_label(w) == r["network"])
        assert r["eps"] == study.size_net(r["system"], widths)[1]
    assert all(p.endswith("size.png") and (tmp_path / "size.png").is_file() for p in sec["figures"])
    assert Table(rows).markdown().count("\n") >= len(rows)


def test_the_largest_network_within_t_s_is_decided_by_cpu_time():
    ms = study.TS * 1e3

    def row(network, hidden, cpu_over, cpu_p90, wall_over, optimal=24, box=None):
        return {"system": "MSD", "network": network, "hidden": hidden, "N_p": 10, "eps": 0.1, "steps": 24,
                "optimal": optimal, "p99 ms": 2 * ms, "max ms": 3 * ms, "over t_s": wall_over,
                "cpu over t_s": cpu_over, "cpu p90 ms": cpu_p90, "binaries (box)": 10 * hidden if box is None else box}

    rows = [row("10x2", 20, 0, 0.2 * ms, 1),        # one step waited for the machine: still within t_s
            row("30x2", 60, 2, 0.5 * ms, 2, box=530),  # two steps computed longer than t_s, the usual ones did not
            row("20x3", 60, 0, 0.3 * ms, 0, 23, box=570),  # a step not proven optimal
            row("40x2", 80, 9, 1.5 * ms, 9)]
    n = study.size_numbers(rows)
    assert n["largest within t_s, MSD N_p=10"] == "10x2"
    # 30x2 and 20x3 have as many neurons: the one with more binaries on the box is the larger, in any row order
    assert n["largest p90 within t_s, MSD N_p=10"] == "20x3"
    assert study.size_numbers(rows[::-1])["largest p90 within t_s, MSD N_p=10"] == "20x3"
    tied = [dict(r, **{"binaries (box)": 550}) for r in rows]  # tied on both: both are named
    assert study.size_numbers(tied)["largest p90 within t_s, MSD N_p=10"] == "30x2 and 20x3"
    assert n["MSD 10x2 N_p=10"]["within"] and not n["MSD 20x3 N_p=10"]["within"]
    assert not n["MSD 40x2 N_p=10"]["p90_within"]
    assert study.size_numbers(rows[3:])["largest within t_s, MSD N_p=10"] is None
