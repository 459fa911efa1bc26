"""Tasks for tests/test_parallel.py, in a module that imports little: a new worker process loads it fast."""
from __future__ import annotations

import os
import signal
import time
from pathlib import Path


def die_once(item):
    """Kill this worker process the first time task 1 runs (a marker file says it happened), else square."""
    k, marker = item
    if k == 1:
        _die_first_time(marker)
    return k * k


def _die_first_time(marker) -> None:
    """Create ``marker`` and kill this worker process, unless ``marker`` exists already."""
    try:
        fd = os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
    except FileExistsError:
        return
    os.close(fd)
    os.kill(os.getpid(), signal.SIGKILL)


def count_calls(item):
    """Leave a file per call in ``folder`` (the task's number, the process, a counter), return ``-k``."""
    k, folder = item
    n = len(list(Path(folder).glob(f"{k}.*")))
    Path(folder, f"{k}.{os.getpid()}.{n}").touch()
    return -k


def fail_on_two(k):
    if k == 2:
        raise ArithmeticError("bad task")
    return k


def die_on_two(k):
    """Kill this worker process every time task 2 runs, else return ``k``."""
    if k == 2:
        os._exit(1)
    return k


def slow_zero_dying_seven(item):
    """Record the call in ``folder``. In the first run task 0 runs on until after task 7 has killed its worker, and
    task 7 kills it (once) only after task 0 has started and the results of tasks 1-6 are in ``stored``."""
    k, folder, stored = item
    count_calls((k, folder))
    marker = Path(folder).parent / "killed"
    if k == 0 and not marker.exists():          # the first run: still running when the pool sees its worker dead
        _wait_for(marker.exists)
        time.sleep(10.0)                        # the pool is shut down meanwhile (the test does not wait for it)
    if k == 7 and not marker.exists():
        _wait_for(lambda: any(Path(folder).glob("0.*")) and len(list(Path(stored).glob("*.pkl"))) >= 6)
        _die_first_time(marker)
    return k * k


def _wait_for(condition, seconds: float = 60.0) -> None:
    """Poll ``condition`` every 0.1 s for at most ``seconds`` (then the test's premise check fails, no hang)."""
    for _ in range(int(seconds * 10)):
        if condition():
            return
        time.sleep(0.1)


def worker_settings(_):
    """This worker process's environment variables of interest and the threads of its BLAS libraries."""
    from threadpoolctl import threadpool_info

    names = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "MALLOC_TOP_PAD_", "OMP_NUM_THREADS",
             "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
    return {k: os.environ.get(k) for k in names}, sorted({p["num_threads"] for p in threadpool_info()
                                                         if p["user_api"] == "blas"})


class CountedPickles:
    """A task function that counts (in a file per pickling) how often it is pickled in the calling process."""

    def __init__(self, folder):
        self.folder = folder

    def __call__(self, k):
        return k + 1

    def __reduce__(self):
        if os.environ.get("FLNOTES_TEST_PARENT") == str(os.getpid()):
            n = len(list(Path(self.folder).glob("pickled.*")))
            Path(self.folder, f"pickled.{n}").touch()
        return CountedPickles, (self.folder,)


def exit_on_one(k):
    """Task 1 calls sys.exit: raised in the caller it would end the program instead of naming the task."""
    import sys

    if k == 1:
        sys.exit(3)
    return k


def generator_result(k):
    """A result that cannot be pickled back to the caller."""
    return (i for i in range(k))


def sleep_zero_fail_one(k):
    """Task 0 runs for a long time, task 1 raises at once."""
    if k == 0:
        time.sleep(60.0)
    if k == 1:
        raise ValueError("bad task")
    return k


def plugins_of(dask_worker):
    return sorted(dask_worker.plugins)
