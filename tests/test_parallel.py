"""flnotes.parallel: the same numbers on 1 worker, 2 local joblib workers and a 2-worker Dask LocalCluster.

The certified bracket, a Monte Carlo table and a sweep table are compared exactly between the three
(the columns that are wall times excepted); a worker killed in the middle of a run either leaves a
run that completes with the same result (Dask reschedules the task) or a clear error and nothing
partial (joblib), after which a rerun resumes from the finished tasks.
"""
from __future__ import annotations

import os
import pickle
import platform
import threading
from pathlib import Path

import numpy as np
import pytest

import flnotes as fl
from flnotes import paper
from flnotes.error import _Rounds, certify_error, pso_max_error
from flnotes.parallel import Executor, TaskFailed, task_key, task_seeds, using
from flnotes.studies import compare as C

from _parallel_tasks import (CountedPickles, count_calls, die_on_two, die_once, exit_on_one, fail_on_two,
                             generator_result, plugins_of, sleep_zero_fail_one, slow_zero_dying_seven, worker_settings)

pytest.importorskip("distributed")


@pytest.fixture(scope="module")
def client():
    from distributed import Client, LocalCluster

    cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                           dashboard_address=None, silence_logs=40)
    cl = Client(cluster)
    yield cl
    cl.close()
    cluster.close()


@pytest.fixture(autouse=True)
def own_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("FLNOTES_CACHE", str(tmp_path / "cache"))


def bounded(job, timeout: float = 90.0):
    """``job()`` in a thread, failed (not waited for) if it takes longer than ``timeout`` seconds: a hang fails."""
    out = {}

    def target():
        try:
            out["value"] = job()
        except BaseException as exc:                                     # re-raised in the test's thread
            out["error"] = exc

    t = threading.Thread(target=target, daemon=True)
    t.start()
    t.join(timeout)
    if t.is_alive():
        pytest.fail(f"no answer within {timeout} s: the run hangs")
    if "error" in out:
        raise out["error"]
    return out["value"]


def engines(client):
    """The three ways to run the same job: (label, keywords)."""
    return [("1 worker", dict(workers=1)), ("2 joblib workers", dict(workers=2)), ("2-worker LocalCluster", dict(client=client))]


def _same(a, b) -> bool:
    return all(np.array_equal(getattr(a, f), getattr(b, f)) for f in ("lower", "upper", "argmax", "n_boxes", "converged"))


# ------------------------------------------------------------------------------ the three jobs
def test_certified_bracket_is_bit_identical_on_every_engine(client):
    sysm = paper.system("Quad-1D")
    net, _ = paper.paper_net("Quad-1D")
    # a small schedule: 1024 boxes bisected per round, 512 per task, so that most rounds have four tasks
    kw = dict(rtol=0.05, batch=1024, chunk=512, n_samples=500)
    whole = certify_error(sysm, net, **{**kw, "chunk": 10**9})          # each round as one evaluation, in process
    assert whole.converged.all() and len(whole.history[0]) > 3         # premise: several rounds were run
    for label, where in engines(client):
        br = certify_error(sysm, net, **kw, **where)
        assert _same(br, whole), label
        assert np.array_equal(br.history[0][:, :2], whole.history[0][:, :2]), label


def test_deep_tasks_give_the_same_bracket_on_every_engine(client):
    """depth > 1: each task bisects its chunk further before it returns; the chunks and what a task does with them
    depend on the round, chunk and depth only, so the bracket is still bit-identical on every engine."""
    sysm = paper.system("Quad-1D")
    net, _ = paper.paper_net("Quad-1D")
    kw = dict(rtol=0.05, batch=1024, chunk=512, n_samples=500, depth=3)
    one = certify_error(sysm, net, **kw)
    assert one.converged.all() and len(one.history[0]) > 2            # premise: several rounds were run
    for label, where in engines(client)[1:]:
        br = certify_error(sysm, net, **kw, **where)
        assert _same(br, one), label
        assert np.array_equal(br.history[0][:, :2], one.history[0][:, :2]), label


_ROUNDS_CALL = _Rounds.__call__            # the real one, before any test patches it


def _interrupt_after(monkeypatch, rounds: int, seen: list):
    """Count the certification's rounds in ``seen``; raise KeyboardInterrupt at round ``rounds`` (0: never)."""
    from flnotes import error

    real = _ROUNDS_CALL

    def counted(self, lo, hi, LB):
        seen.append(len(lo))
        if rounds and len(seen) == rounds:
            raise KeyboardInterrupt("stopped by the test")
        return real(self, lo, hi, LB)

    monkeypatch.setattr(error._Rounds, "__call__", counted)


@pytest.mark.parametrize("depth", [1, 3])
def test_an_interrupted_certification_resumes_to_the_same_bracket(monkeypatch, tmp_path, depth):
    monkeypatch.setenv("FLNOTES_CACHE", str(tmp_path))
    sysm, (net, _) = paper.system("Quad-1D"), paper.paper_net("Quad-1D")
    kw = dict(rtol=0.02, batch=256, chunk=128, n_samples=500, depth=depth, keep_partition=True)
    full_rounds = []
    _interrupt_after(monkeypatch, 0, full_rounds)
    whole = certify_error(sysm, net, **kw)                            # no resume: nothing stored
    assert not (tmp_path / "tasks" / "certify").exists() or not any((tmp_path / "tasks" / "certify").iterdir())
    assert whole.converged.all() and len(full_rounds) > 6             # premise: a run of several rounds
    first = []
    _interrupt_after(monkeypatch, len(full_rounds) // 2, first)
    with pytest.raises(KeyboardInterrupt):
        certify_error(sysm, net, **kw, resume=True, checkpoint_s=0)
    rest = []
    _interrupt_after(monkeypatch, 0, rest)
    resumed = certify_error(sysm, net, **kw, resume=True)
    assert _same(resumed, whole) and np.array_equal(resumed.history[0], whole.history[0])
    for k in ("lo", "hi", "ub"):
        assert np.array_equal(resumed.partition[0][k], whole.partition[0][k])
    # only the rounds not saved before the interruption were run again (the one interrupted, and those after it),
    # besides the first partition's bounds, part of the resume file's key
    assert rest == full_rounds[:1] + full_rounds[len(first) - 1:]
    again = []
    _interrupt_after(monkeypatch, 0, again)
    assert _same(certify_error(sysm, net, **kw, resume=True), whole) and again == full_rounds[:1]   # the end state


def test_a_budget_stopped_certification_goes_on_with_a_larger_budget(monkeypatch, tmp_path):
    monkeypatch.setenv("FLNOTES_CACHE", str(tmp_path))
    sysm, (net, _) = paper.system("Quad-1D"), paper.paper_net("Quad-1D")
    kw = dict(rtol=0.02, batch=256, chunk=128, n_samples=500)
    whole = certify_error(sysm, net, **kw)
    part = certify_error(sysm, net, **kw, max_boxes=2000, resume=True)
    assert not part.converged.all() and part.n_boxes[0] < whole.n_boxes[0]
    assert part.lower[0] <= whole.upper[0] <= part.upper[0]           # sound, only wider
    more = certify_error(sysm, net, **kw, resume=True)
    assert _same(more, whole)
    # another certification (another rtol) does not use that state
    other = certify_error(sysm, net, **{**kw, "rtol": 0.05}, resume=True)
    assert other.n_boxes[0] < whole.n_boxes[0] and other.width[0] <= 0.05 * other.lower[0]


def test_a_damaged_certification_resume_file_is_named(monkeypatch, tmp_path):
    monkeypatch.setenv("FLNOTES_CACHE", str(tmp_path))
    sysm, (net, _) = paper.system("Quad-1D"), paper.paper_net("Quad-1D")
    kw = dict(rtol=0.05, batch=256, chunk=128, n_samples=500)
    certify_error(sysm, net, **kw, resume=True)
    files = list((tmp_path / "tasks" / "certify").glob("*.pkl"))
    assert len(files) == 1
    files[0].write_bytes(b"not a pickle")
    with pytest.raises(ValueError, match=f"resume file .*{files[0].name} cannot be read.*delete"):
        certify_error(sysm, net, **kw, resume=True)
    with pytest.raises(ValueError, match="checkpoint_s .* needs resume=True"):
        certify_error(sysm, net, **kw, checkpoint_s=5.0)
    for bad in (-1.0, "5", True, float("inf")):
        with pytest.raises(ValueError, match="checkpoint_s must be a finite number"):
            certify_error(sysm, net, **kw, resume=True, checkpoint_s=bad)


def _resume_file(tmp_path):
    files = list((tmp_path / "tasks" / "certify").glob("*.pkl"))
    assert len(files) == 1
    return files[0]


def test_a_changed_certification_resume_file_is_refused(monkeypatch, tmp_path):
    """A resume file whose state was changed after it was written (one stored number, a valid pickle) or that holds
    no state is refused, naming the file; never used."""
    monkeypatch.setenv("FLNOTES_CACHE", str(tmp_path))
    sysm, (net, _) = paper.system("Quad-1D"), paper.paper_net("Quad-1D")
    kw = dict(rtol=0.05, batch=256, chunk=128, n_samples=500)
    certify_error(sysm, net, **kw, resume=True)
    path = _resume_file(tmp_path)
    env = pickle.loads(path.read_bytes())
    state = pickle.loads(env["value"])
    state["LB"] = 5.0                                                   # a valid file, one number changed
    path.write_bytes(pickle.dumps({**env, "value": pickle.dumps(state)}))
    with pytest.raises(ValueError, match=f"resume file .*{path.name} was changed after it was written"):
        certify_error(sysm, net, **kw, resume=True)
    from flnotes.parallel import save_checkpoint

    save_checkpoint("certify", path.stem, {"not": "a state"})              # written by the package, but no state
    with pytest.raises(ValueError, match=f"resume file .*{path.name} does not hold a saved state"):
        certify_error(sysm, net, **kw, resume=True)


def test_a_certification_resume_file_is_not_used_for_another_phi(monkeypatch, tmp_path):
    """Two Phi equal at every starting sample, one with a narrow bump between two of them: the second run does not
    resume the first one's state (another key) and finds its own, much larger error."""
    monkeypatch.setenv("FLNOTES_CACHE", str(tmp_path))
    from flnotes import interval as iv

    lo, hi = np.array([-1.0]), np.array([1.0])
    net = fl.ReLUNet([np.array([[1.0], [-1.0]]), np.zeros((1, 2))], [np.zeros(2), np.zeros(1)])   # Phi_NN = 0
    kw = dict(rtol=1e-3, n_samples=50, seed=0)
    x = np.sort(np.random.default_rng(0).uniform(lo, hi, (50, 1))[:, 0])     # the starting samples
    p, s = float(0.5 * (x[20] + x[21])), 1e-4                          # exp(-((x - p) / s)^2) is 0.0 at each

    def f1(X):
        return 0.1 * np.sin(X)

    def f1_iv(X):
        return 0.1 * iv.sin(X)

    def f2(X):
        return 0.1 * np.sin(X) + np.exp(-(((X - p) / s) ** 2))

    def f2_iv(X):
        return 0.1 * iv.sin(X) + iv.exp(-iv.sqr((X - p) / s))

    assert np.array_equal(f1(x[:, None]), f2(x[:, None]))               # premise: equal at the samples
    first = certify_error(f1, net, lo, hi, f_interval=f1_iv, **kw, resume=True)
    second = certify_error(f2, net, lo, hi, f_interval=f2_iv, **kw, resume=True)
    fresh = certify_error(f2, net, lo, hi, f_interval=f2_iv, **kw)
    assert _same(second, fresh) and second.upper[0] > first.upper[0] + 0.5
    # with Lipschitz constants only, Phi is seen at points: resuming is refused
    with pytest.raises(ValueError, match="resume=True needs an interval version of Phi"):
        certify_error(f1, net, lo, hi, lipschitz=2.0, rtol=0.05, resume=True)


def test_certification_progress_bar_changes_nothing(capsys):
    sysm, (net, _) = paper.system("Quad-1D"), paper.paper_net("Quad-1D")
    kw = dict(rtol=0.05, batch=1024, chunk=512, n_samples=500)
    quiet = certify_error(sysm, net, **kw)
    shown = certify_error(sysm, net, **kw, progress=True)
    assert _same(quiet, shown)
    err = capsys.readouterr().err
    assert "certify" in err and "box" in err


def test_certified_bracket_two_outputs_on_a_cluster(client):
    net, _, ref = fl.arm.arm_net()
    sysm = fl.arm.two_link_arm()
    kw = dict(rtol=0.5, batch=128, chunk=64, n_samples=200, max_boxes=1500, initial_per_axis=2)  # seconds, not minutes
    one = certify_error(sysm, net, **kw)
    on_cluster = certify_error(sysm, net, **kw, client=client)
    assert one.lower.shape == (2,) and _same(one, on_cluster)
    assert all(len(h) > 3 for h in one.history)                        # premise: several rounds per output
    assert np.all(one.upper >= one.lower)


def test_pso_restarts_are_the_same_on_every_engine(client):
    sysm = paper.system("MSD")
    net, _ = paper.paper_net("MSD")
    ests = [pso_max_error(sysm, net, n_particles=20, n_iter=20, seed=3, restarts=4, **where) for _, where in engines(client)]
    for e in ests[1:]:
        assert np.array_equal(e.eps, ests[0].eps) and np.array_equal(e.argmax, ests[0].argmax)
    # the best of the restarts is at least each restart run alone with its own seed
    alone = [pso_max_error(sysm, net, n_particles=20, n_iter=20, seed=s).eps[0] for s in task_seeds(3, 4)]
    assert ests[0].eps[0] == max(alone)
    assert ests[0].settings["winner"] == [int(np.argmax(alone))]


def _drop_times(rows, prefixes):
    return [{k: v for k, v in r.items() if not k.startswith(prefixes)} for r in rows]


def test_monte_carlo_table_is_the_same_on_every_engine(client):
    s = C.setting("MSD", horizon=4, time_limit=None)                  # no time limit: plans do not depend on timing
    scenarios = C.draw_scenarios("MSD", 2, seed=5)
    tables = {label: C.monte_carlo(s, scenarios, 0.6, methods=("network", "measured"), **where)
              for label, where in engines(client)}
    ref = tables["1 worker"]
    assert [(r["scenario"], r["method"]) for r in ref] == [(i, m) for i in (0, 1) for m in ("network", "measured")]
    assert all(r["completed"] for r in ref)                           # premise: the runs went to the end
    for label, rows in tables.items():
        # every column but the wall times of the steps and the count of steps slower than t_s, exactly
        a, b = _drop_times(rows, ("ms_", "over_ts")), _drop_times(ref, ("ms_", "over_ts"))
        assert [list(r) for r in a] == [list(r) for r in b], label
        for ra, rb in zip(a, b):
            for k in ra:
                x, y = np.asarray(ra[k]), np.asarray(rb[k])
                same = np.array_equal(x, y, equal_nan=True) if x.dtype.kind == "f" else np.array_equal(x, y)
                assert same, (label, k, ra[k], rb[k])


def test_a_scenario_does_not_depend_on_the_scenarios_run_before_it():
    # One process runs scenario after scenario (1 worker, or a worker given several): a scenario's rows must be
    # those it has alone, or the table would depend on how the scenarios were spread over the workers. Scenario 3
    # after 2 (seed 5, N_p = 4) is a case where the MIQP's LP node bounds carried over from one loop to the next.
    sc = C.draw_scenarios("MSD", 4, seed=5)
    alone = C.run_scenario(C.setting("MSD", horizon=4), sc[3], 0.6, methods=("network",))
    s = C.setting("MSD", horizon=4)
    C.run_scenario(s, sc[2], 0.3, methods=("network",))
    after = C.run_scenario(s, sc[3], 0.6, methods=("network",))
    assert alone[0]["completed"] and alone[0]["steps"] == 6              # premise: the loop ran to its end
    a, b = _drop_times(after, ("ms_", "over_ts")), _drop_times(alone, ("ms_", "over_ts"))
    assert list(a[0]) == list(b[0])
    for k in a[0]:
        x, y = np.asarray(a[0][k]), np.asarray(b[0][k])
        assert np.array_equal(x, y, equal_nan=x.dtype.kind == "f"), (k, a[0][k], b[0][k])


def test_sweep_table_is_the_same_on_every_engine(client):
    msd = fl.msd()
    kw = dict(widths=(3, 4), depths=(1,), n_per_axis=(5,), max_iter=20, n_samples=300, rtol=0.3, max_time=None,
              cache=False, recompute=True)
    tables = {label: fl.studies.architecture_sweep(msd, **kw, **where) for label, where in engines(client)}
    ref = _drop_times(tables["1 worker"], ("train_time", "certify_time"))
    assert [(r["width"], r["depth"], r["n_s"]) for r in ref] == [(3, 1, 5), (4, 1, 5)]
    assert all(r["converged"] for r in ref)
    for label, rows in tables.items():
        assert _drop_times(rows, ("train_time", "certify_time")) == ref, label


# ------------------------------------------------------------------------------ faults and resuming
def test_a_killed_dask_worker_leaves_the_same_result(client, tmp_path):
    marker = str(tmp_path / "killed")
    with using(client=client) as ex:
        out = ex.map(die_once, [(k, marker) for k in range(6)])
    assert Path(marker).exists()                                       # premise: a worker really died mid-run
    assert out == [k * k for k in range(6)]
    client.wait_for_workers(2, timeout=60)                             # the nanny restarts it for the next tests


def test_a_killed_joblib_worker_fails_clearly_then_resumes(tmp_path):
    marker = str(tmp_path / "killed")
    items = [(k, marker) for k in range(6)]
    keys = [task_key("die", k) for k in range(6)]
    with pytest.raises(TaskFailed, match="worker process died.*rerun with the same keys resumes"):
        Executor(workers=2).map(die_once, items, keys=keys, cache="faults")
    assert Path(marker).exists()
    done_before = {p.stem for p in (Path(os.environ["FLNOTES_CACHE"]) / "tasks" / "faults").glob("*.pkl")}
    assert keys[1] not in done_before                                  # nothing of the killed task was kept
    out = Executor(workers=2).map(die_once, items, keys=keys, cache="faults")
    assert out == [k * k for k in range(6)]


def test_resume_runs_only_the_missing_tasks(tmp_path):
    calls = tmp_path / "calls"
    calls.mkdir()
    items = [(k, str(calls)) for k in range(5)]
    keys = [task_key("count", k) for k in range(5)]
    ex = Executor()
    assert ex.map(count_calls, items[:3], keys=keys[:3], cache="count") == [0, -1, -2]
    assert ex.map(count_calls, items, keys=keys, cache="count", progress=True, desc="resume") == [0, -1, -2, -3, -4]
    assert sorted(int(p.name.split(".")[0]) for p in calls.iterdir()) == [0, 1, 2, 3, 4]   # each task ran once


def test_a_failing_task_is_named():
    with pytest.raises(TaskFailed, match="task 2 raised ArithmeticError: bad task"):
        bounded(lambda: Executor(workers=2).map(fail_on_two, range(4)))
    with pytest.raises(ArithmeticError, match="bad task") as info:        # in process: the task's own exception
        Executor(workers=1).map(fail_on_two, range(4))
    assert any("task 2" in n for n in info.value.__notes__)


def test_a_task_that_always_kills_its_dask_worker_is_named():
    # Dask's own allowed-failures decide (KilledWorker), and the task named is the one that kills, not another.
    # A cluster of its own (one worker, as where the failure was seen; the shared cluster is left whole), with
    # allowed-failures 1 so that two deaths suffice; each map runs in a new thread with the same client.
    # worker-saturation 1.0: the scheduler hands the worker one task at a time, so no other task is queued on the
    # worker when it dies (Dask blames every task queued there, and which ones are queued is a matter of timing).
    import dask
    from distributed import Client, LocalCluster

    with dask.config.set({"distributed.scheduler.allowed-failures": 1,
                          "distributed.scheduler.worker-saturation": 1.0}):
        cluster = LocalCluster(n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1",
                               dashboard_address=None, silence_logs=50)
    one = Client(cluster, set_as_default=False)
    try:
        with pytest.raises(TaskFailed, match=r"killed its worker each time") as info:
            bounded(lambda: Executor(client=one, retries=0).map(die_on_two, range(4)))
        named = str(info.value).split(" killed its worker")[0]
        assert "task 2" in named and "task 0" not in named and "task 1" not in named, str(info.value)
        assert "KilledWorker" in repr(info.value.__cause__)
        one.wait_for_workers(1, timeout=60)
        assert bounded(lambda: Executor(client=one).map(die_on_two, [0, 1, 3])) == [0, 1, 3]   # the client is fine
    finally:
        one.close()
        cluster.close()


def test_joblib_keeps_each_result_as_it_arrives(tmp_path):
    # task 0 runs until task 7 has killed its worker; task 7 dies only once task 0 has started and the results of
    # tasks 1-6 are stored (so the order does not depend on how fast each worker starts); the rerun runs only
    # tasks 0 and 7
    calls = tmp_path / "calls"
    calls.mkdir()
    stored = Path(os.environ["FLNOTES_CACHE"]) / "tasks" / "arrive"
    items = [(k, str(calls), str(stored)) for k in range(8)]
    keys = [task_key("arrive", k) for k in range(8)]
    with pytest.raises(TaskFailed, match=r"worker process died.*2 tasks unfinished \(0, 7\).*does not tell which"):
        bounded(lambda: Executor(workers=2).map(slow_zero_dying_seven, items, keys=keys, cache="arrive"))
    assert (tmp_path / "killed").exists()                                # premise: a worker really died
    kept = {p.stem for p in stored.glob("*.pkl")}
    assert kept == set(keys[1:7])
    out = bounded(lambda: Executor(workers=2).map(slow_zero_dying_seven, items, keys=keys, cache="arrive"))
    assert out == [k * k for k in range(8)]
    runs = [int(p.name.split(".")[0]) for p in calls.iterdir()]
    assert sorted(runs) == [0, 0, 1, 2, 3, 4, 5, 6, 7, 7]               # only the unfinished tasks ran again


def test_a_resume_file_of_another_task_is_refused():
    ex, keys = Executor(), [task_key("other", k) for k in range(2)]
    assert ex.map(abs, [-1, -2], keys=keys, cache="swap") == [1, 2]
    folder = Path(os.environ["FLNOTES_CACHE"]) / "tasks" / "swap"
    (folder / f"{keys[1]}.pkl").write_bytes((folder / f"{keys[0]}.pkl").read_bytes())   # copied over from another run
    with pytest.raises(ValueError, match=f"{keys[1]}.pkl holds the result of another task.*delete"):
        ex.map(abs, [-1, -2], keys=keys, cache="swap")


@pytest.mark.parametrize("content", [b"", b"garbage, not a pickle", pickle.dumps({"some": "dict"}), pickle.dumps(4)])
def test_a_damaged_resume_file_is_named(content):
    ex, keys = Executor(), [task_key("damaged", k) for k in range(2)]
    ex.map(abs, [-1, -2], keys=keys, cache="damaged")
    path = Path(os.environ["FLNOTES_CACHE"]) / "tasks" / "damaged" / f"{keys[0]}.pkl"
    path.write_bytes(content)
    with pytest.raises(ValueError, match=f"resume file .*{keys[0]}.pkl (cannot be read|is not a task result).*delete"):
        ex.map(abs, [-1, -2], keys=keys, cache="damaged")
    path.unlink()                                                         # what the message says: then it recomputes
    assert ex.map(abs, [-1, -2], keys=keys, cache="damaged") == [1, 2]


def test_a_function_the_cluster_cannot_receive_is_named(client):
    lock = threading.Lock()

    def holds_a_lock(x):
        with lock:
            return x

    with pytest.raises(TaskFailed, match="holds_a_lock.*cannot be serialized"):
        bounded(lambda: Executor(client=client).map(holds_a_lock, range(2)))


def test_a_closed_client_is_said_to_be_closed(client):
    from distributed import Client

    other = Client(client.scheduler.address, set_as_default=False)
    ex = Executor(client=other)
    other.close()
    with pytest.raises(ValueError, match="client is closed"):
        ex.map(abs, [1])
    with pytest.raises(ValueError, match="client is closed"):
        Executor(client=other)


def test_monte_carlo_refuses_duplicates_with_and_without_resume():
    s = C.setting("MSD", horizon=4, time_limit=None)
    sc = C.draw_scenarios("MSD", 2, seed=5)
    for resume in (False, True):
        with pytest.raises(ValueError, match="methods must be distinct; given more than once: 'network'"):
            C.monte_carlo(s, sc, 0.6, methods=("network", "measured", "network"), resume=resume)
        with pytest.raises(ValueError, match="scenarios must be distinct; given more than once: 1"):
            C.monte_carlo(s, [sc[0], sc[1], sc[1]], 0.6, methods=("network",), resume=resume)


# ------------------------------------------------------------------------------ bad input
def test_bad_options_are_refused(client):
    with pytest.raises(ValueError, match="workers must be an integer >= 1"):
        Executor(workers=0)
    for w in (1, 2):                                                    # documented: not with client, not even 1
        with pytest.raises(ValueError, match="either workers=.*or client="):
            Executor(workers=w, client=client)
    with pytest.raises(TypeError, match="dask.distributed.Client or a scheduler address"):
        Executor(client=3)
    with pytest.raises(ValueError, match="both cache="):
        Executor().map(abs, [1], keys=["a"])
    with pytest.raises(ValueError, match="one key per task"):
        Executor().map(abs, [1, 2], keys=["a"], cache="x")
    with pytest.raises(ValueError, match="plain name"):
        Executor().map(abs, [1], keys=["a"], cache="../x")
    with pytest.raises(ValueError, match="one finite number per task"):
        Executor().map(abs, [1, 2], cost=[1.0])
    assert Executor(client=client).map(abs, [-1, -2, -3], cost=[1.0, 3.0, 2.0]) == [1, 2, 3]   # started 2, 3, 1
    with pytest.raises(ValueError, match="chunk must be an integer >= 1"):
        certify_error(paper.system("MSD"), paper.paper_net("MSD")[0], chunk=0)
    with pytest.raises(ValueError, match="restarts must be an integer >= 1"):
        pso_max_error(paper.system("MSD"), paper.paper_net("MSD")[0], restarts=0)
    assert Executor(workers=2).engine == "joblib" and Executor().engine == "serial"
    assert Executor(client=client).engine == "dask" and Executor(client=client).workers == 2


def test_command_lines_take_workers_or_a_scheduler():
    from flnotes.bench import parse_args
    from flnotes.parallel import parse_workers
    from flnotes.studies.shipped import main as shipped_main

    assert parse_workers(["--workers", "3", "x"]) == (3, None, ["x"])
    assert parse_workers(["--scheduler=tcp://127.0.0.1:8786"]) == (None, "tcp://127.0.0.1:8786", [])
    for bad, msg in ((["--workers"], "needs a value"), (["--workers", "two"], "whole number"),
                     (["--workers", "2", "--scheduler", "tcp://a:1"], "not both"),
                     (["--workers", "1", "--scheduler", "tcp://a:1"], "not both"),
                     (["--workers", "2", "--workers", "3"], "--workers is given twice"),
                     (["--scheduler", "tcp://a:1", "--scheduler=tcp://b:2"], "--scheduler is given twice")):
        with pytest.raises(ValueError, match=msg):
            parse_workers(bad)
    assert parse_args(["--fast", "--workers", "2", "error"]) == dict(fast=True, workers=2, scheduler=None,
                                                                     sections=["error"])
    with pytest.raises(ValueError, match="unknown section"):
        parse_args(["nosuch"])
    assert shipped_main(["--workers", "0"]) == 2 and shipped_main(["nosuch"]) == 2


def test_local_workers_start_with_one_blas_thread_and_the_allocator_settings():
    from flnotes.config import MALLOC_SETTINGS

    with Executor(workers=2) as ex:
        seen = ex.map(worker_settings, range(4))
    for env, threads in seen:
        assert {k: env[k] for k in MALLOC_SETTINGS} == {k: str(v) for k, v in MALLOC_SETTINGS.items()}
        assert env["OMP_NUM_THREADS"] == env["OPENBLAS_NUM_THREADS"] == env["MKL_NUM_THREADS"] == "1"
        assert threads in ([], [1])                                      # every BLAS library found uses one thread


def test_the_task_function_is_pickled_once_per_map(tmp_path, monkeypatch):
    monkeypatch.setenv("FLNOTES_TEST_PARENT", str(os.getpid()))        # count the picklings in this process only
    with Executor(workers=2) as ex:
        assert ex.map(CountedPickles(str(tmp_path)), range(12)) == list(range(1, 13))
    assert len(list(tmp_path.glob("pickled.*"))) == 1                  # not once per task (12)


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc only")
def test_keep_freed_memory_applies_on_glibc():
    from flnotes.config import keep_freed_memory

    assert keep_freed_memory() is True


def test_a_task_that_exits_or_returns_what_cannot_be_pickled_is_named():
    with Executor(workers=2) as ex:
        with pytest.raises(TaskFailed, match=r"task 1 raised SystemExit"):
            ex.map(exit_on_one, range(3))
        with pytest.raises(TaskFailed, match=r"task \d failed on its worker"):
            ex.map(generator_result, range(3))
        assert ex.map(abs, [-1, -2]) == [1, 2]                          # the caller's process is still usable


def test_a_failed_map_does_not_leave_its_running_tasks_to_the_next():
    with Executor(workers=2) as ex:
        with pytest.raises(TaskFailed, match="task 1 raised ValueError"):
            bounded(lambda: ex.map(sleep_zero_fail_one, range(2)), 30.0)
        assert bounded(lambda: ex.map(abs, [-3, -4]), 30.0) == [3, 4]    # not after task 0's 60 s


def test_on_a_cluster_too_a_task_that_exits_or_returns_what_cannot_be_pickled_is_named(client):
    ex = Executor(client=client)
    with pytest.raises(TaskFailed, match=r"task 1 raised TaskExit: SystemExit: 3"):
        bounded(lambda: ex.map(exit_on_one, range(3)))
    with pytest.raises(TaskFailed, match=r"task \d ended but its result could not be fetched"):
        bounded(lambda: ex.map(generator_result, range(3)))
    assert len(client.nthreads()) == 2 and ex.map(abs, [-1, -2]) == [1, 2]    # no worker lost


def test_dask_workers_get_the_allocator_plugin(client):
    Executor(client=client)
    seen = client.run(plugins_of)
    assert seen and all("flnotes-keep-freed-memory" in p for p in seen.values())


def test_a_cluster_without_workers_fails_instead_of_waiting_for_ever(monkeypatch):
    from distributed import Client, LocalCluster

    import flnotes.parallel as P

    monkeypatch.setattr(P, "NO_WORKERS_TIMEOUT", 2.0)
    with LocalCluster(n_workers=0, processes=True, host="127.0.0.1", dashboard_address=None) as cluster, \
            Client(cluster) as cl:
        with pytest.raises(TaskFailed, match="no worker for 2 s"):
            bounded(lambda: Executor(client=cl).map(abs, [-1, -2]), 30.0)


def test_a_round_is_cut_into_an_even_number_of_equal_chunks():
    from flnotes.error import MIN_CHUNK, chunk_sizes

    for n in (0, 1, 2 * MIN_CHUNK - 1, 2 * MIN_CHUNK, 1016, 1840, 3376, 7808, 8192, 8193):
        for c in (64, 512, 1024):
            sizes = chunk_sizes(n, c)
            assert sum(sizes) == n and max(sizes, default=0) - min(sizes, default=0) <= 1, (n, c)
            if n < 2 * min(MIN_CHUNK, c):
                assert sizes == ([n] if n else []), (n, c)             # a small round stays whole, in process
            else:
                assert len(sizes) % 2 == 0 and max(sizes) <= c and len(sizes) - 2 < n / c, (n, c)
    assert chunk_sizes(8192, 1024) == [1024] * 8 and chunk_sizes(3376, 1024) == [844] * 4


def test_scaling_model_saturates_where_it_should():
    from flnotes.bench.parallel import scaling_model

    n, t_box, t_ser, o = 1_000_000, 100e-6, 5e-6, 2e-3
    fixed = {r["workers"]: r for r in scaling_model(n, t_box, t_ser, o, workers=(1, 2, 8, 32), batch=4096, chunk=1024)}
    assert fixed[1]["speedup"] == 1.0 and fixed[1]["chunks_per_round"] == 8 and fixed[1]["tasks_per_round"] == 0
    assert fixed[2]["tasks_per_round"] == 2 and fixed[32]["tasks_per_round"] == 8    # one task per busy worker
    assert 1.0 < fixed[2]["speedup"] < 2.0                       # the serial part and the overhead cost something
    assert fixed[32]["wall_s"] == fixed[8]["wall_s"]               # 8 chunks per round: no gain beyond 8 workers
    scaled = {r["workers"]: r for r in scaling_model(n, t_box, t_ser, o, workers=(8, 128, 4096), scale_batch=True)}
    floor = n * (t_ser + o / 1024)
    assert scaled[128]["wall_s"] < fixed[8]["wall_s"] and scaled[4096]["wall_s"] > floor
    assert scaled[4096]["wall_s"] < 1.2 * floor                    # beyond W_half the time is the serial floor
    assert scaled[8]["W_half"] == pytest.approx(t_box / (t_ser + o / 1024))
    with pytest.raises(ValueError):
        scaling_model(0, t_box, t_ser, o)
    # a round's latency: every round that leaves the process pays it once (123 rounds' worth of work: 122 full and
    # one partial), the rounds growing from the first partition too (256 .. 4096 boxes: 5), or a given count
    plain = {r["workers"]: r for r in scaling_model(n, t_box, t_ser, o, workers=(1, 2))}
    trip = {r["workers"]: r for r in scaling_model(n, t_box, t_ser, o, workers=(1, 2), round_trip=0.02)}
    assert trip[1]["wall_s"] == plain[1]["wall_s"] and trip[2]["rounds"] == 123
    assert trip[2]["wall_s"] - plain[2]["wall_s"] == pytest.approx(123 * 0.02)
    ramp = scaling_model(n, t_box, t_ser, o, workers=(2,), round_trip=0.02, first_boxes=256)[0]
    assert ramp["rounds"] == 128 and ramp["wall_s"] - trip[2]["wall_s"] == pytest.approx(5 * 0.02)
    given = scaling_model(n, t_box, t_ser, o, workers=(2,), round_trip=0.02, rounds=10)[0]
    assert given["rounds"] == 10 and given["wall_s"] - plain[2]["wall_s"] == pytest.approx(10 * 0.02)
    # deeper tasks: the same work in fewer rounds, so less latency
    deep = scaling_model(n, t_box, t_ser, o, workers=(2,), round_trip=0.02, depth=8)[0]
    assert deep["rounds"] == 16 and deep["wall_s"] < trip[2]["wall_s"]
