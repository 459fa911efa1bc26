"""One way to run independent tasks in parallel: local processes (joblib) or a Dask cluster.

Every job of the package whose work splits into independent tasks (the boxes of a
certification round, PSO restarts, the scenarios of a Monte Carlo, the networks of a
sweep, the shipped references, the benchmark's sections) runs them through
:class:`Executor`. Three engines, one contract:

``"serial"``
    ``workers=1`` (the default of every job): the tasks run one after the other in this
    process, as before this module existed;
``"joblib"``
    ``workers=N`` (N > 1): N local worker processes (:mod:`joblib`'s reusable ``loky`` process
    pool), each with one BLAS thread and glibc's allocator keeping freed memory (:func:`worker_env`);
``"dask"``
    ``client=`` a :class:`dask.distributed.Client` or a scheduler address
    (``"tcp://host:8786"``): the tasks go to whatever cluster the client is connected to (a
    ``LocalCluster``, ``dask-jobqueue`` on a batch system, Kubernetes); a task whose worker dies
    is re-run on another worker (Dask's own rescheduling, up to its ``allowed-failures``; ``retries``
    re-runs a task that raised).

The contract that makes the engines interchangeable:

* **the same numbers**: a task is a pure function of its arguments (a task that draws random
  numbers gets its own seed, :func:`task_seeds`), and :meth:`Executor.map` returns the results
  in the order of submission, so a reduction over them is the same whatever the number of
  workers or the engine;
* **no silent partial result**: a task that fails on a worker, or a worker that dies and is not
  re-run, raises :class:`TaskFailed` naming the task (in this process, the task's own exception is
  raised, with a note naming it); :meth:`Executor.map` never returns fewer results than tasks;
* **resumable**: with ``cache=`` (a name) and ``keys=`` (one string per task), each finished
  result is stored in the package's cache folder (:func:`flnotes.config.cache_dir`) as soon as it
  arrives, and a later run with the same keys loads it instead of running the task again; each file
  stores its key with the result and is checked when loaded: a damaged file, or one holding another
  task's result, is refused with a ``ValueError`` naming it (delete it to recompute that task);
* **progress**: ``progress=True`` shows a :mod:`tqdm` bar (a widget in a notebook).

No scheduler, queue or socket of our own: joblib and Dask do that.
"""
from __future__ import annotations

import hashlib
import json
import os
import pickle
import time
from contextlib import contextmanager
from functools import partial
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Optional, Sequence

import numpy as np

from .config import MALLOC_SETTINGS, cache_dir, one_blas_thread

__all__ = ["Executor", "TaskFailed", "using", "task_seeds", "task_key", "measure_overhead", "measure_round_trip",
           "parse_workers", "worker_env", "save_checkpoint", "load_checkpoint", "checkpoint_path"]

ENGINES = ("serial", "joblib", "dask")


class TaskFailed(RuntimeError):
    """A task of :meth:`Executor.map` failed or lost its worker; no partial result is returned."""


def task_seeds(seed: int, n: int) -> list[int]:
    """``n`` independent seeds for ``n`` tasks, derived from ``seed`` (:class:`numpy.random.SeedSequence`).

    Task ``k`` always gets the same seed, whichever worker runs it and however many there are.
    """
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    return [int(s.generate_state(1, np.uint64)[0] >> np.uint64(1)) for s in np.random.SeedSequence(seed).spawn(n)]


def task_key(*parts: Any) -> str:
    """A short stable key of a task's arguments (JSON of ``parts``, SHA-1), for :meth:`Executor.map` ``keys=``."""
    blob = json.dumps(parts, sort_keys=True, default=lambda o: getattr(o, "tolist", lambda: repr(o))())
    return hashlib.sha1(blob.encode()).hexdigest()[:16]


def _run(fn: Callable, item: Any) -> Any:
    """One task on a worker: one BLAS thread, so that N workers use N cores."""
    with one_blas_thread():
        return fn(item)


class TaskExit(RuntimeError):
    """A task on a Dask worker raised ``SystemExit`` or ``KeyboardInterrupt`` (which would end the worker)."""


def _run_on_cluster(fn: Callable, item: Any) -> Any:
    """One task on a Dask worker (:func:`_run`); ``SystemExit`` and ``KeyboardInterrupt`` raised by the task are turned
    into :class:`TaskExit`, a task error that names the task, instead of ending the worker and the tasks queued on it."""
    try:
        return _run(fn, item)
    except (SystemExit, KeyboardInterrupt) as exc:
        raise TaskExit(f"{type(exc).__name__}: {exc}") from None


def _run_indexed(fn: Callable, k: int, item: Any) -> tuple:
    """One task on a local worker: ``(k, True, result)``, or ``(k, False, exception)`` if it raised.

    ``SystemExit`` and ``KeyboardInterrupt`` raised by the task are returned too: re-raised in the caller they would
    end its program instead of naming the task.
    """
    try:
        return k, True, _run(fn, item)
    except (Exception, SystemExit, KeyboardInterrupt) as exc:
        return k, False, exc


#: Threads of the numerical libraries in a local worker process: one, so that N workers use N cores.
_ONE_THREAD = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS",
               "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS")


def worker_env() -> dict[str, str]:
    """The environment variables a local worker process starts with.

    One thread per numerical library (as joblib's ``inner_max_num_threads=1``), and glibc's allocator keeping
    freed memory for reuse (:data:`flnotes.config.MALLOC_SETTINGS`; other C libraries ignore these variables).
    """
    return {**{v: "1" for v in _ONE_THREAD}, **{k: str(v) for k, v in MALLOC_SETTINGS.items()}}


class _Shipped:
    """A task function pickled once (cloudpickle) for all the tasks of a map, unpickled once per worker process."""

    def __init__(self, fn: Callable):
        import cloudpickle

        self.blob = cloudpickle.dumps(fn)

    def __reduce__(self):
        return _unship, (self.blob,)


_UNSHIPPED: dict = {}


def _unship(blob: bytes) -> Callable:
    """The function of a :class:`_Shipped` blob; the last few are kept, so a worker unpickles each once."""
    key = hashlib.sha1(blob).digest()
    fn = _UNSHIPPED.get(key)
    if fn is None:
        if len(_UNSHIPPED) >= 8:
            _UNSHIPPED.clear()
        fn = _UNSHIPPED[key] = pickle.loads(blob)
    return fn


_FORMAT = "flnotes.parallel result 2"


def _save(path: Path, key: str, value: Any) -> None:
    """Write one task's result with its key and a SHA-256 of its bytes, atomically (a temporary file, then a rename)."""
    blob = pickle.dumps(value)
    tmp = path.with_name(f"{path.stem}.{os.getpid()}.tmp")
    tmp.write_bytes(pickle.dumps({"format": _FORMAT, "key": key, "sha256": hashlib.sha256(blob).hexdigest(),
                                  "value": blob}))
    tmp.replace(path)


def _load(path: Path, key: str) -> Any:
    """The result stored in ``path`` for the task ``key``; ``ValueError`` naming the file if it is not that.

    A file that cannot be read, that is not a result file of :meth:`Executor.map` (or of this version of the
    package), whose stored bytes do not match their SHA-256 (changed after they were written), or that holds the
    result of another task (another key: copied from another run) is refused, never used and never silently
    recomputed: deleting it makes the next run compute that task again.
    """
    fix = f"delete {path} (or the whole folder {path.parent} to start fresh) and run again"
    try:
        env = pickle.loads(path.read_bytes())
    except Exception as exc:
        raise ValueError(f"the resume file {path} cannot be read ({type(exc).__name__}: {exc}): it is damaged; "
                         f"{fix}") from exc
    if not (isinstance(env, dict) and env.get("format") == _FORMAT and {"key", "sha256", "value"} <= set(env)
            and isinstance(env["value"], bytes)):
        raise ValueError(f"the resume file {path} is not a task result written by this version of flnotes.parallel "
                         f"(it holds a {type(env).__name__}); {fix}")
    if env["key"] != key:
        raise ValueError(f"the resume file {path} holds the result of another task (key {env['key']!r}, "
                         f"not {key!r}): it was copied or renamed from another run; {fix}")
    if hashlib.sha256(env["value"]).hexdigest() != env["sha256"]:
        raise ValueError(f"the resume file {path} was changed after it was written (its SHA-256 does not match): it "
                         f"is damaged; {fix}")
    try:
        return pickle.loads(env["value"])
    except Exception as exc:
        raise ValueError(f"the resume file {path} cannot be read ({type(exc).__name__}: {exc}): it is damaged; "
                         f"{fix}") from exc


def checkpoint_path(cache: str, key: str) -> Path:
    """Where :func:`save_checkpoint` keeps the state ``key`` of a long job: ``cache_dir()/tasks/<cache>/<key>.pkl``."""
    return _task_folder(cache) / f"{key}.pkl"


def save_checkpoint(cache: str, key: str, state: Any) -> None:
    """Store the state ``key`` of a long job (written atomically with its key, as :meth:`Executor.map`'s results)."""
    _save(checkpoint_path(cache, key), key, state)


def load_checkpoint(cache: str, key: str, fields: Sequence[str] = ()) -> Any:
    """The state stored by :func:`save_checkpoint` for ``key``; ``None`` when there is none. A damaged file, one
    that holds another job's state, or one whose state is not a dict with ``fields``, is refused with a
    ``ValueError`` naming it (never used, never ignored)."""
    path = checkpoint_path(cache, key)
    if not path.exists():
        return None
    state = _load(path, key)
    missing = [f for f in fields if not isinstance(state, dict) or f not in state]
    if missing:
        raise ValueError(f"the resume file {path} does not hold a saved state (missing {', '.join(missing)}): it is "
                         f"damaged; delete it and run again")
    return state


def _is_client(obj: Any) -> bool:
    return type(obj).__name__ == "Client" and type(obj).__module__.startswith("distributed")


class Executor:
    """Runs independent tasks in this process, in local worker processes, or on a Dask cluster.

    Parameters
    ----------
    workers
        Number of local worker processes; 1 (default) runs the tasks in this process, N > 1 uses
        joblib's ``loky`` processes with one BLAS thread each. Not with ``client`` (not even 1).
    client
        A :class:`dask.distributed.Client`, or a scheduler address (str) to which one is connected
        (and closed again by :meth:`close`). The cluster's workers get the allocator settings of the local
        workers (:data:`flnotes.config.MALLOC_SETTINGS`) through a worker plugin, registered once under the name
        ``"flnotes-keep-freed-memory"``, also on workers that join later: Dask starts its workers with
        ``MALLOC_TRIM_THRESHOLD_=65536``, which made a certification on a 2-worker ``LocalCluster`` 12 times slower
        than in one process. A map fails with :class:`TaskFailed` when the cluster has had no worker for
        :data:`NO_WORKERS_TIMEOUT` seconds.
    retries
        Dask only: times a task that raised (or was declared ``KilledWorker``) is re-submitted; 0 by
        default, for a task is a pure function of its arguments (it would raise again). A task whose
        worker dies is rescheduled by the scheduler itself, up to distributed's ``allowed-failures``
        times (config ``distributed.scheduler.allowed-failures``, 3 by default), after which it fails
        with ``KilledWorker`` and :meth:`map` raises :class:`TaskFailed` naming it; each retry starts that
        count again.

    Examples
    --------
    >>> with Executor(workers=2) as ex:                       # doctest: +SKIP
    ...     squares = ex.map(pow2, range(10), progress=True)
    """

    def __init__(self, workers: Optional[int] = None, client: Any = None, retries: int = 0):
        if client is not None and workers is not None:
            raise ValueError(f"give either workers={workers} (local processes) or client= (a Dask cluster), not both: "
                             f"the cluster's size is set where the cluster is started")
        if not isinstance(retries, (int, np.integer)) or retries < 0:
            raise ValueError(f"retries must be an integer >= 0, got {retries!r}")
        self.retries = int(retries)
        self._own_client = False
        self.client = None
        if client is not None:
            if isinstance(client, str):
                from distributed import Client

                client = Client(client)
                self._own_client = True
            elif not _is_client(client):
                raise TypeError(f"client must be a dask.distributed.Client or a scheduler address such as "
                                f"'tcp://127.0.0.1:8786', got {type(client).__name__}")
            _check_open(client)
            self.client = client
            self.engine = "dask"
            _tune_dask_workers(client)
            self.workers = max(1, len(client.nthreads()))          # the cluster's workers now
            return
        w = 1 if workers is None else workers
        if isinstance(w, bool) or not isinstance(w, (int, np.integer)) or w < 1:
            raise ValueError(f"workers must be an integer >= 1 (the number of local processes), got {workers!r}")
        self.workers = int(w)
        self.engine = "serial" if self.workers == 1 else "joblib"

    def __repr__(self) -> str:
        where = f" at {self.client.scheduler.address}" if self.client is not None else ""
        return f"Executor({self.engine}, {self.workers} worker{'s' if self.workers != 1 else ''}{where})"

    def __enter__(self) -> "Executor":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Close the Dask client if this executor opened it (from an address)."""
        if self._own_client and self.client is not None:
            self.client.close()
            self.client = None

    # ------------------------------------------------------------------ the one method
    def map(self, fn: Callable[[Any], Any], items: Iterable[Any], *, keys: Optional[Sequence[str]] = None,
            cache: Optional[str] = None, desc: Optional[str] = None, progress: bool = False,
            cost: Optional[Sequence[float]] = None) -> list:
        """``[fn(item) for item in items]``, run in parallel; the results in the order of ``items``.

        Parameters
        ----------
        fn
            A function of one argument, picklable (a module-level function, or a closure: joblib and
            Dask pickle it with cloudpickle). It must not depend on anything but its argument: that is
            what makes the result independent of the engine.
        items
            The tasks' arguments.
        keys, cache
            Resume: with ``cache`` (a name, e.g. ``"montecarlo"``) and ``keys`` (one stable string per
            task, see :func:`task_key`), each result is written to ``cache_dir()/tasks/<cache>/<key>.pkl``
            as it arrives (with its key) and loaded from there by a later run. Both or neither. A file
            that cannot be read or holds another key's result is refused (``ValueError`` naming the file).
        desc, progress
            A :mod:`tqdm` progress bar labelled ``desc``.
        cost
            One guess of the run time per task (any unit): on workers the tasks start in decreasing ``cost``
            (ties in the order of ``items``), so that a long task does not start last and keep one worker busy
            while the others wait. In this process the tasks run in the order of ``items``. Only the order in
            which the tasks start depends on it, never the results or their order.

        Raises
        ------
        TaskFailed
            On workers: a task raised, or its worker died and it could not be re-run; the message names
            the task (joblib cannot tell which task's process died: the message lists the unfinished
            ones). In this process (``workers=1``) a task's exception is raised as it is, with a note
            naming the task. Either way the results already finished stay in the cache (if any) for the
            next run, and no partial list is returned.
        ValueError
            Bad options, a closed Dask client, or a resume file that cannot be used (named).
        """
        items = list(items)
        if cost is not None:
            cost = np.asarray(cost, float)
            if cost.shape != (len(items),) or not np.all(np.isfinite(cost)):
                raise ValueError(f"cost must give one finite number per task ({len(items)}), got shape {cost.shape}")
        if (keys is None) != (cache is None):
            raise ValueError("resuming needs both cache= (a name) and keys= (one per task), or neither")
        if keys is not None and len(keys) != len(items):
            raise ValueError(f"keys has {len(keys)} entries for {len(items)} tasks: give one key per task")
        if keys is not None and len(set(keys)) != len(keys):
            raise ValueError("keys must be distinct: two tasks with the same key would share a cached result")
        folder = _task_folder(cache) if cache is not None else None
        if self.client is not None:
            _check_open(self.client)
        results: list = [None] * len(items)
        todo = []
        for k in range(len(items)):
            if folder is not None and (folder / f"{keys[k]}.pkl").is_file():
                results[k] = _load(folder / f"{keys[k]}.pkl", keys[k])
            else:
                todo.append(k)
        start = todo if cost is None else sorted(todo, key=lambda k: -cost[k])   # stable: ties in item order
        bar = _bar(len(items), len(items) - len(todo), desc, progress)
        finished = set(range(len(items))) - set(todo)

        def done(k: int, value: Any) -> None:
            results[k] = value
            finished.add(k)
            if folder is not None:
                _save(folder / f"{keys[k]}.pkl", keys[k], value)
            if bar is not None:
                bar.update(1)

        def name(k: int) -> str:
            return f"task {k}" + (f" (key {keys[k]})" if keys is not None else "") + (f" of {desc!r}" if desc else "")

        def resume() -> str:
            return (f"; the {len(finished)} of {len(items)} results finished are kept in {folder} and a rerun with "
                    f"the same keys resumes from them" if folder is not None else "")

        def unfinished() -> str:
            left = [k for k in start if k not in finished]
            shown = ", ".join(map(str, left[:10])) + (", ..." if len(left) > 10 else "")
            return f"{len(left)} task{'s' if len(left) != 1 else ''} unfinished ({shown})"

        try:
            if self.engine == "serial" or not todo:
                for k in todo:           # in this process: a task's own exception, as without an executor
                    try:
                        value = _run(fn, items[k])
                    except Exception as exc:
                        exc.add_note(f"(in {name(k)}{resume()})")
                        raise
                    done(k, value)
            elif self.engine == "joblib":
                self._map_joblib(fn, items, start, done, name, unfinished, resume)
            else:
                self._map_dask(fn, items, start, done, name, resume)
        finally:
            if bar is not None:
                bar.close()
        return results

    def _map_joblib(self, fn, items, todo, done, name, unfinished, resume) -> None:
        from concurrent.futures import FIRST_COMPLETED, wait

        from joblib.externals.loky import get_reusable_executor
        from joblib.externals.loky.process_executor import TerminatedWorkerError

        # joblib's reusable loky process pool, driven through its futures: ``joblib.Parallel`` looks for finished
        # tasks every 10 ms (a sleep in its result loop), which a certification pays once per round of short
        # tasks (2 workers: x1.34 instead of x1.74 on the MSD). The tasks start in the order of ``todo``, one per
        # free worker, and each result is stored as soon as it ends; ``map`` puts them back in the order of the
        # items. The function is pickled once for all the tasks (:class:`_Shipped`).
        pool = get_reusable_executor(max_workers=self.workers, env=worker_env())
        task = _Shipped(fn)
        futures: dict = {}
        finished = False
        try:
            for k in todo:
                futures[pool.submit(_run_indexed, task, k, items[k])] = k
            pending = set(futures)
            while pending:
                ended, pending = wait(pending, return_when=FIRST_COMPLETED)
                for fut in sorted(ended, key=futures.__getitem__):
                    k = futures[fut]
                    try:
                        _, ok, value = fut.result()
                    except TerminatedWorkerError:
                        raise
                    except Exception as exc:   # e.g. a result that cannot be pickled back to this process
                        raise TaskFailed(f"{name(k)} failed on its worker: {type(exc).__name__}: {exc} (a result "
                                         f"that cannot be pickled?); no partial result is returned{resume()}") from exc
                    if not ok:
                        raise TaskFailed(f"{name(k)} raised {type(value).__name__}: {value}{resume()}") from value
                    done(k, value)
            finished = True
        except TerminatedWorkerError as exc:
            raise TaskFailed(f"a local worker process died (killed, or out of memory) with {unfinished()}; joblib "
                             f"does not tell which of them was running on it; no partial result is returned"
                             f"{resume()}. ({exc.__class__.__name__})") from exc
        finally:
            if not finished:
                # a task failed, or this process was interrupted (KeyboardInterrupt): cancel the tasks not started and
                # stop the workers still running tasks of this map (as joblib does), so that the next map does not
                # wait for them; the next map starts new workers
                for fut in futures:
                    fut.cancel()
                if any(f.running() for f in futures):
                    pool.shutdown(wait=False, kill_workers=True)

    def _map_dask(self, fn, items, todo, done, name, resume) -> None:
        import queue

        client = self.client
        prefix = f"flnotes-{getattr(fn, '__name__', 'task')}-{time.time_ns()}"
        try:
            futures = client.map(partial(_run_on_cluster, fn), [items[k] for k in todo], pure=False,  # fn sent once
                                 retries=self.retries, key=[f"{prefix}-{k}" for k in todo])
        except Exception as exc:   # the function or an argument cannot be serialized for the cluster
            raise TaskFailed(f"the tasks could not be sent to the cluster: the function {_fn_name(fn)} or an "
                             f"argument cannot be serialized ({type(exc).__name__}: {exc}); make it a module-level "
                             f"function of picklable arguments") from exc
        which = {f.key: k for f, k in zip(futures, todo)}
        pending = dict(zip(todo, futures))
        ended: queue.Queue = queue.Queue()
        for fut in futures:      # called by the client's own thread when the task ends: no event loop of this thread
            fut.add_done_callback(ended.put)
        del futures
        try:
            # A result is fetched as soon as its task ends and the future is released at once, so that a worker
            # dying later does not take the result with it; a task whose worker dies is rescheduled by the
            # scheduler alone, which after distributed's allowed-failures declares it KilledWorker (naming the
            # task that kills its worker). No retry loop here.
            no_workers_since = None
            while pending:
                try:
                    fut = ended.get(timeout=1.0)
                except queue.Empty:
                    _check_open(client)          # a client closed meanwhile: say so rather than wait for ever
                    if client.nthreads():
                        no_workers_since = None
                    elif no_workers_since is None:
                        no_workers_since = time.monotonic()
                    elif time.monotonic() - no_workers_since > NO_WORKERS_TIMEOUT:
                        raise TaskFailed(f"the Dask cluster has had no worker for {NO_WORKERS_TIMEOUT:g} s (all died, "
                                         f"or none started) with {len(pending)} task(s) waiting; restart or scale up "
                                         f"the cluster and run again; no partial result is returned{resume()}")
                    continue
                k = which[fut.key]
                if k not in pending:         # told twice
                    continue
                if fut.status == "error":
                    exc = fut.exception()
                    if type(exc).__name__ == "KilledWorker":
                        # Dask blames every task that was on the dying worker, queued ones too: collect the tasks
                        # it declares KilledWorker within a few seconds and name them all, in order
                        killed = {which.get(getattr(exc, "task", None), k)}
                        t_end = time.monotonic() + 5.0
                        while time.monotonic() < t_end and len(killed) < len(pending):
                            try:
                                other = ended.get(timeout=0.5)
                            except queue.Empty:
                                continue
                            j = which[other.key]
                            if other.status == "error" and type(other.exception()).__name__ == "KilledWorker":
                                killed.add(j)
                            elif other.status == "finished" and j in pending:  # kept for a resume
                                value = other.result()
                                del pending[j]
                                other.release()
                                done(j, value)
                        tasks = ", ".join(name(j) for j in sorted(killed))
                        msg = (f"{tasks} killed its worker each time it ran (distributed's allowed-failures, config "
                               f"distributed.scheduler.allowed-failures; Dask blames every task that was running or "
                               f"queued on the worker that died, so with several named the culprit is among them): "
                               f"{exc}")
                    else:
                        msg = f"{name(k)} raised {type(exc).__name__}: {exc}"
                    raise TaskFailed(f"{msg}; no partial result is returned{resume()}") from exc
                if fut.status == "cancelled":
                    raise TaskFailed(f"{name(k)} was cancelled on the cluster (the client or the scheduler "
                                     f"closed?); no partial result is returned{resume()}")
                try:
                    value = fut.result()
                except Exception as exc:   # e.g. a result the worker could not serialize
                    raise TaskFailed(f"{name(k)} ended but its result could not be fetched from the cluster "
                                     f"({type(exc).__name__}: {exc}; a result that cannot be pickled?); no partial "
                                     f"result is returned{resume()}") from exc
                del pending[k]
                fut.release()
                done(k, value)
        finally:
            left = list(pending.values())
            if left and client.status == "running":
                client.cancel(left)


def _tune_dask_workers(client: Any) -> None:
    """Give the cluster's workers the allocator settings of the local workers (a worker plugin, registered once).

    Dask starts its workers with ``MALLOC_TRIM_THRESHOLD_=65536``: glibc then gives freed memory back at once and a
    certification's chunks map their arrays anew each time (measured: a 2-worker ``LocalCluster`` certifying the MSD
    12 times slower than one process). The plugin applies :data:`flnotes.config.MALLOC_SETTINGS` with ``mallopt`` in
    each worker process, also in workers that join later (a no-op where the C library is not glibc).
    """
    from ._dask_plugins import KeepFreedMemory

    client.register_plugin(KeepFreedMemory(), name=KeepFreedMemory.name)


#: Seconds a Dask map waits while the cluster has no worker at all before it fails (all workers died, or none
#: started): the tasks would otherwise wait for ever.
NO_WORKERS_TIMEOUT = 60.0


def _fn_name(fn: Callable) -> str:
    f = fn.func if isinstance(fn, partial) else fn
    return repr(getattr(f, "__qualname__", type(f).__name__))


def _check_open(client: Any) -> None:
    if client.status != "running":
        raise ValueError(f"the Dask client is closed (status {client.status!r}): connect a new Client to the "
                         f"cluster, or pass its scheduler address as client=")


@contextmanager
def using(workers: Optional[int] = None, client: Any = None) -> Iterator[Executor]:
    """The :class:`Executor` of a job's ``workers=`` and ``client=`` keywords, as a context.

    ``client`` may be a Dask client, a scheduler address or an :class:`Executor` (used as it is, and
    left open); an executor made here is closed at the end (a client opened from an address too).
    """
    if isinstance(client, Executor):
        if workers is not None:
            raise ValueError("give either workers= or an Executor as client=, not both")
        yield client
        return
    ex = Executor(workers=workers, client=client)
    try:
        yield ex
    finally:
        ex.close()


def _task_folder(cache: str) -> Path:
    if not isinstance(cache, str) or not cache or any(c in cache for c in "/\\") or cache.startswith("."):
        raise ValueError(f"cache must be a plain name such as 'montecarlo' (a folder of the cache), got {cache!r}")
    path = cache_dir() / "tasks" / cache
    path.mkdir(parents=True, exist_ok=True)
    return path


def _bar(total: int, initial: int, desc: Optional[str], progress: bool):
    if not progress:
        return None
    from tqdm.auto import tqdm

    return tqdm(total=total, initial=initial, desc=desc, unit="task")


def _noop(x: Any) -> Any:
    return x


def measure_overhead(executor: Executor, n_tasks: int = 200) -> float:
    """Seconds per task that the engine adds when many trivial tasks are in flight (its throughput: ``n_tasks``
    submitted at once, the wall time divided by ``n_tasks``).

    The cost of each task beyond the first ones of a round in the scaling model
    (:func:`flnotes.bench.parallel.scaling_model`); a round's own latency is :func:`measure_round_trip`.
    """
    executor.map(_noop, range(min(n_tasks, 2 * executor.workers)))     # warm the workers up
    t0 = time.perf_counter()
    executor.map(_noop, range(n_tasks))
    return (time.perf_counter() - t0) / n_tasks


def measure_round_trip(executor: Executor, n_maps: int = 50) -> float:
    """Median seconds of one map of ``executor.workers`` trivial tasks, waited for before the next: the latency a
    dependent round pays (a branch-and-bound round cannot start before the last one has answered)."""
    executor.map(_noop, range(2 * executor.workers))                     # warm the workers up
    times = []
    for _ in range(n_maps):
        t0 = time.perf_counter()
        executor.map(_noop, range(executor.workers))
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def parse_workers(argv: Sequence[str]) -> tuple[Optional[int], Optional[str], list[str]]:
    """The options ``--workers N`` and ``--scheduler ADDRESS`` of a command line: ``(workers, scheduler, rest)``.

    ``ValueError`` saying what to change for a missing or bad value, an option given twice, or both options
    given (even ``--workers 1``).
    """
    workers, scheduler, rest = None, None, []
    it = iter(argv)
    for a in it:
        key, eq, val = a.partition("=")
        if key not in ("--workers", "--scheduler"):
            rest.append(a)
            continue
        val = val if eq else next(it, "")
        if not val or val.startswith("--"):
            raise ValueError(f"{key} needs a value: --workers N (local processes) or --scheduler ADDRESS "
                             f"(a Dask scheduler, e.g. tcp://127.0.0.1:8786)")
        if (workers if key == "--workers" else scheduler) is not None:
            raise ValueError(f"{key} is given twice: give it once")
        if key == "--workers":
            if not val.isdigit() or int(val) < 1:
                raise ValueError(f"--workers must be a whole number >= 1, got {val!r}")
            workers = int(val)
        else:
            scheduler = val
    if workers is not None and scheduler is not None:
        raise ValueError("give --workers N (local processes) or --scheduler ADDRESS (a Dask cluster), not both")
    return workers, scheduler, rest
