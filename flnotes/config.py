"""Run-time switches shared by the book, the tests and the benchmarks.

``FLNOTES_FAST=1`` in the environment makes the notebooks do less (shorter
simulations, coarser grids, fewer samples) so that the test suite runs in
minutes; ``make book`` leaves it unset and runs everything at full scale.
Tests still check the real properties, only on less data.
"""
from __future__ import annotations

import _signal  # signal's C module: see release_signals
import gc
import numbers
import os
import signal
import sys
import threading
from contextlib import contextmanager
from functools import lru_cache
from pathlib import Path
from typing import Optional, TypeVar

T = TypeVar("T")

#: True when the environment variable ``FLNOTES_FAST`` is set to a true value.
FAST: bool = os.environ.get("FLNOTES_FAST", "").strip().lower() in {"1", "true", "yes", "on"}


def scale(full: T, fast: T) -> T:
    """Return ``fast`` under ``FLNOTES_FAST=1`` and ``full`` otherwise.

    Examples
    --------
    >>> t_final = scale(full=20.0, fast=3.0)
    """
    return fast if FAST else full


def cache_dir() -> Path:
    """Folder where trained networks and certified bounds are cached.

    ``FLNOTES_CACHE`` overrides it; the default is ``_build/flnotes-cache``
    beside the book when run from a checkout, else ``~/.cache/flnotes``.
    """
    env = os.environ.get("FLNOTES_CACHE")
    if env:
        path = Path(env)
    else:
        repo = Path(__file__).resolve().parent.parent
        path = repo / "_build" / "flnotes-cache" if (repo / "_toc.yml").exists() else Path.home() / ".cache" / "flnotes"
    path.mkdir(parents=True, exist_ok=True)
    return path


#: glibc's allocator settings for processes that evaluate many large numpy temporaries (a certification's chunk of
#: 1024 boxes allocates about 7 MB of arrays of 160 kB each, and frees them): map only blocks above 32 MB, give the
#: heap back to the system only when 64 MB at its top are free, and grow it 16 MB at a time. With glibc's defaults
#: that memory is given back and mapped anew on every chunk (3,100 page faults, a quarter of the chunk's time in the
#: kernel). The local worker processes of :class:`flnotes.parallel.Executor` start with these settings
#: (environment variables read by glibc at start), the workers of a Dask cluster given to it get them through a worker
#: plugin, and :func:`keep_freed_memory` applies them to a running process.
MALLOC_SETTINGS: dict[str, int] = {"MALLOC_MMAP_THRESHOLD_": 32 << 20, "MALLOC_TRIM_THRESHOLD_": 64 << 20,
                                   "MALLOC_TOP_PAD_": 16 << 20}

_MALLOPT = {"MALLOC_TRIM_THRESHOLD_": -1, "MALLOC_TOP_PAD_": -2, "MALLOC_MMAP_THRESHOLD_": -3}   # glibc's M_* codes


def keep_freed_memory() -> bool:
    """Apply :data:`MALLOC_SETTINGS` to this process (glibc's ``mallopt``); ``True`` if applied.

    For a process that runs certifications (:func:`flnotes.certify_error`) itself, ``workers=1``: the local
    worker processes already start with these settings, and a Dask cluster's workers get them when an
    :class:`flnotes.parallel.Executor` is made for it. The process then keeps up to 64 MB of freed memory for
    reuse instead of giving it back to the system at once, and glibc no longer adapts its thresholds (the
    settings stay until the process ends). Returns ``False``, changing nothing, where the C library is not glibc
    (macOS, Windows, musl).
    """
    import ctypes
    import ctypes.util

    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name) if name else None
        mallopt = libc.mallopt if libc is not None else None
        gnu = libc is not None and hasattr(libc, "gnu_get_libc_version")
    except (OSError, AttributeError):
        return False
    if mallopt is None or not gnu:
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return all(mallopt(_MALLOPT[k], v) == 1 for k, v in MALLOC_SETTINGS.items())


_POOLS = None
_BLAS_LOCK = threading.Lock()
#: The entries of :func:`one_blas_thread` now inside it, one token each: adding or removing a token is one step,
#: which an interrupt (Ctrl-C) cannot split, where a count read and written back could be left off by one.
_BLAS_HOLDERS: set = set()
#: The BLAS libraries' thread counts from before the first entry set them to one, kept until they are all set back:
#: a setting back that an interrupt stopped half-way is completed, with these counts, by the next last exit.
_BLAS_ORIGINAL: Optional[list] = None


@contextmanager
def one_blas_thread():
    """A context in which the BLAS libraries loaded by numpy and scipy use one thread (:mod:`threadpoolctl`).

    A controller step works on small matrices. With several BLAS threads on a busy machine each product
    waits for the other threads to be scheduled: with two threads, two processes on two cores made steps of
    the book's MPC that take about 0.1 s take 1 to 3 s. After a product OpenBLAS's other threads also spin for a
    while, waiting for the next one: on a 20 ms controller whose engine's solve ran on after an answer at the
    cut-off (with two BLAS threads, the step's context having ended), that spinning thread took 20 to 50 ms of the
    next step's core, and its answer came at up to 3.7 times the limit. :class:`flnotes.MPC` and
    :class:`flnotes.ClfCbfController` run every step inside this context; a time-limited MPC step that answers at
    its cut-off keeps it until its engine's solve has ended (set back by the next step, ``reset()`` or ``finish()``).

    The setting is process-wide, so the context is shared: the limit is set when the first entry finds none and the
    previous counts come back when the last one leaves. The counts are taken before the limit is set and kept until
    they are back, so that an interrupt (Ctrl-C) at any point of an entry or an exit never leaves the limit of one in
    place, nor takes it for the process's own setting. OpenBLAS ignores a thread count raised from a thread other
    than the one that set it lower, so leave the context in the thread that entered it.
    """
    global _POOLS, _BLAS_ORIGINAL
    token = object()
    try:
        with _BLAS_LOCK:
            _BLAS_HOLDERS.add(token)
            if len(_BLAS_HOLDERS) == 1:
                if _POOLS is None:
                    from threadpoolctl import ThreadpoolController

                    _POOLS = ThreadpoolController()
                blas = [lib for lib in _POOLS.lib_controllers if lib.user_api == "blas"]
                if _BLAS_ORIGINAL is None:  # else a setting back was stopped half-way: its counts are the originals
                    _BLAS_ORIGINAL = [(lib, lib.num_threads) for lib in blas]
                for lib in blas:
                    lib.set_num_threads(1)
        yield
    finally:
        with _BLAS_LOCK:
            _BLAS_HOLDERS.discard(token)
            if not _BLAS_HOLDERS and _BLAS_ORIGINAL is not None:
                for lib, n in _BLAS_ORIGINAL:
                    lib.set_num_threads(n)
                _BLAS_ORIGINAL = None


#: Seconds after which a thread that waits for Python's interpreter lock asks the running thread for it, inside
#: :func:`quick_thread_switch` (Python's default, :func:`sys.getswitchinterval`, is 5 ms).
SWITCH_INTERVAL_S = 0.0002


_SWITCH_LOCK = threading.Lock()
#: The entries of :func:`quick_thread_switch` now inside it, one token each (see :data:`_BLAS_HOLDERS`).
_SWITCH_HOLDERS: set = set()
_SWITCH_WAS = None


@contextmanager
def quick_thread_switch(interval: float = SWITCH_INTERVAL_S):
    """A context in which a thread waiting for the interpreter lock gets it within ``interval`` seconds.

    A thread running Python code keeps the interpreter lock until another thread has waited for it for
    :func:`sys.getswitchinterval` (5 ms by default), and takes it back after as long. When :class:`flnotes.MPC`
    answers at its cut-off while its engine's solve still runs Python code in its worker thread, every time the
    answering thread needs the lock it can wait that long (seen on a 20 ms controller: answers 5 to 9 ms after
    the cut-off for well under 1 ms of work, and, with the interval restored as the step returned while the solve
    ran on, 3.7 ms between the step's last line and its caller). A step under a time limit runs in this context and,
    when it answers at its cut-off, keeps it until its engine's solve has ended (set back by the next step,
    ``reset()`` or ``finish()``). Only threads that compete for the
    lock switch more often: a step whose answering thread waits (the engine alone runs Python code) is not slowed.

    The interval is process-wide, so the context is shared: each entry lowers the interval to at most ``interval``
    and the interval the first entry found comes back when the last one leaves; an interrupt (Ctrl-C) at any point of
    an entry or an exit leaves neither the short interval in place nor takes it for the process's own.
    """
    global _SWITCH_WAS
    if not interval > 0.0:
        raise ValueError(f"interval must be a positive number of seconds, got {interval!r}")
    token = object()
    try:
        with _SWITCH_LOCK:
            _SWITCH_HOLDERS.add(token)
            if _SWITCH_WAS is None:  # else a setting back was stopped before it was recorded: the value is the same
                _SWITCH_WAS = sys.getswitchinterval()
            sys.setswitchinterval(min(sys.getswitchinterval(), float(interval)))
        yield
    finally:
        with _SWITCH_LOCK:
            _SWITCH_HOLDERS.discard(token)
            if not _SWITCH_HOLDERS and _SWITCH_WAS is not None:
                sys.setswitchinterval(_SWITCH_WAS)
                _SWITCH_WAS = None


#: Slice (seconds) the thread that answers a time-limited :class:`flnotes.MPC` step asks of Linux's scheduler inside
#: :func:`answer_slice` (EEVDF's shortest, 0.1 ms; the default is 0.75 ms times 1 + log2 of the cores, capped at 3 ms).
ANSWER_SLICE_S = 1e-4

#: ``(sched_setattr, sched_getattr)`` system call numbers per machine (Linux's ``struct sched_attr`` interface).
_SCHED_ATTR_CALLS = {"x86_64": (314, 315), "aarch64": (274, 275)}


@lru_cache(maxsize=None)
def _sched_attr():
    """The ``struct sched_attr`` type and the two system calls, or ``None`` where this is not Linux on a known machine."""
    import ctypes
    import platform

    calls = _SCHED_ATTR_CALLS.get(platform.machine())
    if not sys.platform.startswith("linux") or calls is None:
        return None

    class SchedAttr(ctypes.Structure):
        _fields_ = [("size", ctypes.c_uint32), ("sched_policy", ctypes.c_uint32), ("sched_flags", ctypes.c_uint64),
                    ("sched_nice", ctypes.c_int32), ("sched_priority", ctypes.c_uint32),
                    ("sched_runtime", ctypes.c_uint64), ("sched_deadline", ctypes.c_uint64),
                    ("sched_period", ctypes.c_uint64), ("sched_util_min", ctypes.c_uint32),
                    ("sched_util_max", ctypes.c_uint32)]

    try:
        libc = ctypes.CDLL(None, use_errno=True)
    except OSError:  # pragma: no cover - no C library
        return None
    return ctypes, SchedAttr, libc.syscall, calls


def thread_run_delay(tid: Optional[int] = None) -> float:
    """Seconds a thread has spent runnable but waiting for a CPU since it started (Linux: its ``schedstat``, the
    second field): the calling thread's, or that of the thread of this process with native id ``tid``
    (:func:`threading.get_native_id`); NaN where the platform does not say or the thread has ended.

    The difference of two readings tells, of the time a thread took to resume after a timed wait, how much it waited
    for a core; the rest it was not runnable (its timer had not fired, or it waited for the interpreter lock)."""
    path = "/proc/thread-self/schedstat" if tid is None else f"/proc/self/task/{int(tid)}/schedstat"
    try:
        fd = os.open(path, os.O_RDONLY)
        try:
            data = os.read(fd, 256)
        finally:
            os.close(fd)
        return int(data.split()[1]) * 1e-9
    except (OSError, IndexError, ValueError):
        return float("nan")


def major_faults() -> float:
    """The major page faults of this process so far (``getrusage``'s ``ru_majflt``: pages read back from disk, such as
    a shared library's code that the operating system had dropped from memory); NaN where the platform does not say.

    A thread that touches such a page waits for the disk without running or waiting for a core, so the difference of
    two readings tells a delay of the machine from the controller's own work."""
    try:
        import resource
    except ImportError:  # pragma: no cover - not on Unix
        return float("nan")
    return float(resource.getrusage(resource.RUSAGE_SELF).ru_majflt)


def machine_steal() -> float:
    """The time, in seconds, during which the host of this virtual machine ran something else while the machine's
    CPUs had work for it (the ``steal`` column of Linux's ``/proc/stat``, summed over the machine's CPUs; its
    resolution is one clock tick, 1/``SC_CLK_TCK``: 10 ms on most systems); NaN where the system does not say
    (not Linux, or a kernel without the column). On a machine that is not virtual it stays 0.

    While the host takes a CPU, the thread that ran on it neither runs (its CPU time stands still) nor waits for a
    core in its own system's eyes: the difference of two readings tells such a delay of the machine from the
    controller's own work (``info["steal_time"]`` of :class:`flnotes.MPC`)."""
    try:
        with open(_PROC_STAT, "rb") as f:
            return _steal_seconds(f.readline())
    except OSError:
        return float("nan")


_PROC_STAT = "/proc/stat"
_TICKS_PER_SECOND = float(os.sysconf("SC_CLK_TCK")) if hasattr(os, "sysconf") else float("nan")


def _steal_seconds(line: bytes) -> float:
    """The steal time of the ``cpu`` line of ``/proc/stat`` (the 8th number after the label), in seconds."""
    fields = line.split()
    if len(fields) < 9 or fields[0] != b"cpu":
        return float("nan")
    return int(fields[8]) / _TICKS_PER_SECOND


def thread_slice() -> Optional[int]:
    """The calling thread's scheduler slice in nanoseconds (Linux's ``sched_getattr``: ``sched_runtime`` of a thread
    of the normal policy), or ``None`` where it cannot be read (another system, another policy, a refused call)."""
    got = _get_attr()
    return None if got is None or got.sched_policy != 0 else int(got.sched_runtime)


def _get_attr():
    api = _sched_attr()
    if api is None:
        return None
    ctypes, SchedAttr, syscall, (_, get_call) = api
    attr = SchedAttr()
    if syscall(get_call, 0, ctypes.byref(attr), ctypes.sizeof(SchedAttr), 0) != 0:
        return None
    return attr


#: ``sched_flags`` bit of a thread that resets its policy in children (``SCHED_RESET_ON_FORK``), kept by the slice changes.
_RESET_ON_FORK = 0x01


def _set_slice(runtime_ns: int) -> bool:
    """Set the calling thread's slice (``sched_runtime``; 0: the default), keeping its policy, nice value, priority
    and reset-on-fork flag as they are now (read just before). Only for the normal policy; whether it was accepted."""
    cur = _get_attr()
    if cur is None or cur.sched_policy != 0:
        return False
    ctypes, SchedAttr, syscall, (set_call, _) = _sched_attr()
    new = SchedAttr(size=48, sched_policy=cur.sched_policy, sched_flags=int(cur.sched_flags) & _RESET_ON_FORK,
                    sched_nice=cur.sched_nice, sched_priority=cur.sched_priority, sched_runtime=int(runtime_ns))
    return syscall(set_call, 0, ctypes.byref(new), 0) == 0


def set_back_slice(runtime_ns: Optional[int]) -> None:
    """Give the calling thread the slice ``runtime_ns`` it had (as read by :func:`thread_slice`): its default slice
    when that is what it had, else that custom slice. ``None`` (nothing was read): nothing is changed.

    A thread created inside :func:`answer_slice` inherits the short slice (Linux copies it to new threads); the
    engine's thread of a time-limited :class:`flnotes.MPC` step calls this first, with the slice its creator had
    before the step (:func:`slice_before_answer`), so that it solves with the slice it had always had.
    """
    if runtime_ns is None:
        return
    _set_slice(0)  # the default slice ...
    after = thread_slice()
    if after is not None and after != int(runtime_ns):
        _set_slice(int(runtime_ns))  # ... or the custom slice the thread had


_ANSWER = threading.local()  # per thread: the slices before the answer_slice contexts it is in (innermost last)


def slice_before_answer() -> Optional[int]:
    """The calling thread's slice (ns) before the innermost :func:`answer_slice` context it is in that was granted,
    ``None`` outside one (or where none was granted)."""
    stack = getattr(_ANSWER, "before", None)
    return stack[-1] if stack else None


@contextmanager
def answer_slice(seconds: float = ANSWER_SLICE_S):
    """A context in which the calling thread asks Linux's scheduler for a short slice; yields whether it got it.

    A time-limited :class:`flnotes.MPC` step waits, in its answering thread, for its engine's thread until the
    cut-off, then answers. Waking then, the answering thread needs a core that its engine's thread or another
    process holds. With the default slice (0.75 to 3 ms, by the number of cores) the running thread keeps the core
    to the end of its slice: with a busy process on the other core of a 2-core machine, the answering thread of a
    20 ms controller waited 3 to 6 ms for a core at nearly every cut-off. Linux's EEVDF scheduler (kernel 6.12 and
    later) lets a thread of the normal policy ask for a shorter slice (``sched_setattr``'s ``sched_runtime``,
    0.1 to 100 ms, no privilege needed); a thread with a shorter slice has an earlier deadline and takes the core
    when it wakes. The slice is the only thing changed (policy, nice value, priority and the reset-on-fork flag are
    kept, as they are when it is set and when it is set back, so a nice value changed inside the context stays) and
    is set back when the context ends: the thread's default slice, or the custom slice it had before. Threads
    started inside the context inherit the short slice; :func:`set_back_slice` with :func:`slice_before_answer`
    gives one back its creator's slice. Elsewhere (another system, an older kernel that ignores the request, a
    thread of another policy, a refused call) nothing is changed and the context yields ``False``.
    """
    if not (isinstance(seconds, numbers.Real) and not isinstance(seconds, bool) and 1e-4 <= float(seconds) <= 0.1):
        raise ValueError(f"seconds must be a slice between 1e-4 and 0.1 s (Linux's range), got {seconds!r}")
    want = int(round(float(seconds) * 1e9))
    before = thread_slice()
    got = pushed = False
    stack = _ANSWER.__dict__.setdefault("before", [])
    try:  # the slice is asked for inside: an interrupt (Ctrl-C) anywhere still sets it back
        if before is not None and _set_slice(want):
            got = thread_slice() == want
            if not got:  # a kernel without custom slices: leave the thread as it was
                set_back_slice(before)
        if got:
            stack.append(before)
            pushed = True
        yield got
    finally:
        if pushed:
            stack.pop()
        if got or (before is not None and thread_slice() != before):
            set_back_slice(before)


#: Nice value given at the cut-off to the engine's thread of a time-limited :class:`flnotes.MPC` step (Linux).
CUT_OFF_NICE = 10


def yield_core(native_id: Optional[int], nice: int = CUT_OFF_NICE) -> bool:
    """Lower the scheduling priority of one thread of this process to ``nice``; whether it was done.

    At its cut-off a time-limited :class:`flnotes.MPC` step answers while its engine's solver call may still run
    in C (DAQP, HiGHS, SCIP do not stop in mid-call). On a machine with fewer free cores than runnable threads the
    answering thread then shares a core with it; at nice 10 the engine's thread gets about a tenth of that core
    (Linux's CFS weights 1024 against 110) and the answer the rest. The thread ends after its call (each step
    starts a new thread at this process's own priority), so nothing stays lowered. Linux only, where a thread
    has its own nice value (``os.setpriority`` with its native id); elsewhere, for an unknown or ended thread, or
    when the system refuses, nothing is changed and the answer is ``False``. The priority is only ever lowered.
    """
    if native_id is None or not sys.platform.startswith("linux") or not hasattr(os, "setpriority"):
        return False
    try:
        if os.getpriority(os.PRIO_PROCESS, int(native_id)) >= nice:
            return True
        os.setpriority(os.PRIO_PROCESS, int(native_id), int(nice))
    except OSError:                       # the thread has ended (ESRCH), or the system refused (EACCES, EPERM)
        return False
    return True


#: The signals :func:`hold_signals` holds back when Python handles them: every one a handler can be set for.
_HELD_SIGNALS: tuple = tuple(int(s) for s in sorted(signal.valid_signals())
                             if s not in {getattr(signal, n, None) for n in ("SIGKILL", "SIGSTOP")})
_INDEX: dict = {s: i for i, s in enumerate(_HELD_SIGNALS)}
#: The handlers :func:`hold_signals` replaced by :func:`_hold`, by position in ``_HELD_SIGNALS`` (``None``: not
#: replaced). An entry stays until its handler is back, also when a release is cut short (see :func:`_hold`).
_OLD: list = [None] * len(_HELD_SIGNALS)
#: The signals that came while held, ``(signum, frame, handler)`` in the order they came, one per arrival.
_DEFERRED: list = []
_HOLDING = False  # between hold_signals and release_signals (main thread only)
_FLUSHING = False  # while _flush delivers: a held signal that comes then is noted and delivered by the same loop
_HELD = object()  # hold_signals' answer when it holds


def _hold(signum, frame) -> None:
    """The handler of every held signal: while held (or while the held signals are delivered), note the signal for
    :func:`release_signals`; otherwise (a handler left in place by a release that a handler's exception cut
    short) put the signal's own handler back and deliver to it now, after the signals noted before it."""
    i = _INDEX[signum]
    handler = _OLD[i]
    if handler is None:  # pragma: no cover - _hold is installed only with the handler it replaced saved, and that
        return  # entry is cleared only once the handler is back
    _DEFERRED.append((signum, frame, handler))  # every arrival Python handles, as its handler would have run for each
    if not (_HOLDING or _FLUSHING):
        try:
            _put_back(i)
        finally:  # also when another signal's handler raises as it is put back: this one is noted, deliver it
            _flush()


def _put_back(i: int) -> None:
    """Put back the handler saved at position ``i`` if the hold's is still in place (a handler set meanwhile is kept),
    then forget it. :func:`signal.signal` first runs the handlers of signals that came: when one of them sets a handler
    for this signal, that one is kept (from the handler ``signal.signal`` answers it replaced)."""
    s, old = _HELD_SIGNALS[i], _OLD[i]
    if old is not None and _signal.getsignal(s) is _hold:
        replaced = _signal.signal(s, old)
        if replaced is not _hold:  # set by a handler that ran inside the call: keep it
            _signal.signal(s, replaced)
    _OLD[i] = None  # only once the handler is back: an exception before leaves the entry for a later try


def _restore() -> None:
    """Put back every handler :func:`hold_signals` replaced, unless it has been changed meanwhile (a handler set
    inside the step is kept). Signal's C functions: they allocate nothing. A handler put back runs at once when its
    signal comes; when it raises, the rest are put back all the same, then its exception is raised."""
    err, i, n = None, 0, len(_HELD_SIGNALS)
    while i < n:
        try:
            while i < n:  # each entry may be redone (after an exception): it is put back or cleared, never twice
                if _OLD[i] is not None:
                    _put_back(i)
                i += 1
        except BaseException as exc:
            if err is None:
                err = exc
    if err is not None:
        raise err


def _flush() -> None:
    """Deliver the signals noted while held, in the order they came, each to the handler in place when it came, called
    directly (not raised again through the system, where the main thread may block it or a wakeup file descriptor
    would see it twice). Every one is delivered, also when a handler raises: the first handler's exception is raised
    once the list is empty. A held signal that comes meanwhile is noted and delivered by the same loop (see
    :func:`_hold`), so that none is left noted when the loop ends."""
    global _FLUSHING
    was, _FLUSHING = _FLUSHING, True  # (a handler delivered here may run a step: its own release flushes inside)
    err = None
    try:
        while _DEFERRED:  # again when another handler's exception escaped the inner loop between two deliveries
            try:
                while _DEFERRED:
                    try:
                        signum, frame, handler = _DEFERRED[0]
                        del _DEFERRED[0]  # no call between taking the entry and the handler's: nothing runs between
                        handler(signum, frame)
                    except BaseException as exc:
                        if err is None:
                            err = exc
            except BaseException as exc:
                if err is None:
                    err = exc
    finally:  # reached from the loop's last test of the list with nothing run in between
        _FLUSHING = was
    if err is not None:
        raise err


def hold_signals() -> Optional[object]:
    """Hold back every signal that Python handles (Ctrl-C's SIGINT, a timeout's SIGALRM, a SIGTERM handler, ...) in
    the main thread until :func:`release_signals`; its answer is what :func:`release_signals` needs (``None``: nothing
    was changed: another thread, no handler of Python's, or already held by an outer call).

    A time-limited :class:`flnotes.MPC` step changes process-wide settings (the cyclic collector paused, one BLAS
    thread, a short switch interval) and shares threading primitives with its solve's thread. An exception raised by a
    signal's handler between two lines of it could leave the collector paused for good, or land inside one of those
    primitives (CPython does not make them safe against such exceptions: an alarm's exception inside the start of the
    solve's thread, or inside a wait for it, once left the solve's thread and then ``finish()`` waiting for good).
    The step lasts about ``t_s``, so the signals are held back for that long and then delivered to their handlers, once
    every setting is back (:func:`release_signals`). Handlers set in C (or ``SIG_DFL``, ``SIG_IGN``) are left alone.

    A signal that comes while the handlers are replaced, before the step, runs its handler there (an exception of it
    comes out of this call, with nothing held), and so does one that an earlier hold left noted
    (:func:`release_signals`). Replacing and putting back a handler goes through :func:`signal.signal`, with two
    effects on the system's side that Python cannot read back: a :func:`signal.siginterrupt` setting of a held signal
    is reset to interrupting system calls, and a handler chained in C over Python's
    (``faulthandler.register(signum, chain=True)`` on a signal that also has a Python handler) is replaced by Python's
    own: register such handlers on signals without a Python handler."""
    global _HOLDING
    if _HOLDING or threading.current_thread() is not threading.main_thread():
        return None
    if _DEFERRED:  # left noted by an earlier delivery that two signals at once cut short: delivered before the hold
        _flush()
    # signal's C functions over lists made in advance, which allocate nothing: a step calls this first, before it
    # pauses the collector; _HOLDING is set first, so that a held signal that comes meanwhile is noted, not delivered
    _HOLDING = True
    try:
        changed = False
        for i in range(len(_HELD_SIGNALS)):
            s = _HELD_SIGNALS[i]
            old = _signal.getsignal(s)
            if old is _hold:  # left in place by a release cut short: its handler is still saved
                changed = True
            elif callable(old):  # not SIG_DFL, SIG_IGN or a C handler (None)
                _OLD[i] = old
                replaced = _signal.signal(s, _hold)  # runs a signal that came just before first (its own handler)
                if replaced is not old and replaced is not _hold:  # that handler set another one: hold that one,
                    if callable(replaced):  # or leave it (SIG_DFL, SIG_IGN)
                        _OLD[i] = replaced
                    else:
                        _signal.signal(s, replaced)
                        _OLD[i] = None
                        continue
                changed = True
    except BaseException:  # a handler not yet replaced raised (a signal that came as the hold began): nothing held,
        _HOLDING = False  # first (no call before it), then the end of a hold: a signal noted meanwhile is delivered
        try:
            release_signals(_HELD)
        except BaseException:  # another handler's exception at its very start: the handlers are put back all the same
            _restore()
            raise
        raise
    if not changed:
        _HOLDING = False
        return None
    return _HELD


def release_signals(held: Optional[object]) -> None:
    """End :func:`hold_signals` (``held`` its answer): the handlers come back, and each signal held back meanwhile is
    delivered to its handler now, as often as Python handled it while held (the system itself merges arrivals that
    come before Python handles the first), in the order they came, by a direct call (Python's default handler of
    Ctrl-C raises ``KeyboardInterrupt``); every one is delivered even when an earlier handler raises, and the first
    handler's exception is raised after the last. A handler set while held (by code inside the step) is not held
    back, and is kept.

    The held signals are delivered before the handlers are put back, so that a signal that comes meanwhile is
    delivered after them. When a handler's exception cuts the putting back short (a signal that came just then), a
    handler not yet put back is put back at its signal's next arrival (and delivered to) or at the next hold's end.
    When several signals whose handlers raise are pending at once (CPython runs one at each point where it checks for
    signals, so each such point can raise), the delivery can be cut short too: what is left noted is delivered at the
    start of the next hold (:func:`hold_signals`), or with the next arrival of a signal still held.
    """
    global _HOLDING
    if held is None:
        return
    _HOLDING = False
    try:  # the held signals first, while every handler is still the hold's: one that comes meanwhile is delivered
        _flush()  # after them (see _hold), whatever its handler does
    finally:
        try:
            _restore()
        except BaseException:  # a handler's exception at its start or between its rounds: once more
            _restore()
            raise


_GC_LOCK = threading.RLock()
_GC_USERS = 0
_GC_WAS = False


class no_cyclic_gc:  # noqa: N801 - used as a function, like the other contexts of this module
    """A context in which Python's cyclic garbage collector does not run (reference counting still frees memory).

    A full collection walks every object the collector tracks: about 40 ms once numpy, scipy, the solvers and a
    controller are loaded (100,000 objects), 0.8 of a 50 ms sampling period, and it starts whenever enough objects
    have survived, inside whatever code is running. :class:`flnotes.MPC` runs a step under a time limit in this
    context, so a collection never lands inside the call: the collector is paused before the step allocates
    anything and resumed as its last action, and a collection that fell due meanwhile starts at the caller's next
    allocation of a tracked object, after the call has returned (a collection started by the first allocation after
    the resume, still inside the call, once made answers 2 to 4 times late while their record said on time). A step
    answered at its cut-off keeps the collector paused until its engine's solve has ended (the solve's thread holds
    a pause of its own and ends it as it ends), so that the solve's thread, running on, does not start a collection
    that holds the interpreter lock while the caller's code or the next step needs it. A loop whose time between
    answers is shorter than a collection can call :func:`gc.freeze` once it is set up (the objects alive then are no
    longer walked).

    The setting is process-wide, so the context is shared: the first entry pauses the collector when it runs, and
    the last one to leave resumes it (when the first found it running). Entering and leaving allocate no object
    that the collector tracks (:func:`pause_gc`, :func:`resume_gc`).
    """

    __slots__ = ()

    def __enter__(self) -> None:
        pause_gc()

    def __exit__(self, exc_type, exc, tb) -> None:
        resume_gc()


def pause_gc() -> None:
    """Pause the cyclic collector (shared, see :class:`no_cyclic_gc`), before allocating anything it tracks: a call
    that starts with this cannot start a collection (the ``with`` statement allocates before it enters). Every
    :func:`pause_gc` needs its :func:`resume_gc` (in a ``finally``)."""
    global _GC_USERS, _GC_WAS
    _GC_LOCK.acquire()  # the state is read and changed under the lock: two threads pausing and resuming at once
    try:  # cannot make the last resume find the collector paused by the other
        if _GC_USERS == 0:
            _GC_WAS = gc.isenabled()
        gc.disable()
        _GC_USERS += 1
    finally:
        _GC_LOCK.release()


def resume_gc() -> None:
    """End a :func:`pause_gc`: the last one to end resumes the collector (when the first found it running), as its
    last action and allocating nothing, so that a collection that fell due starts at the caller's next allocation."""
    global _GC_USERS
    _GC_LOCK.acquire()
    try:
        if _GC_USERS <= 0:
            raise RuntimeError("resume_gc() without a pause_gc() before it")
        _GC_USERS -= 1
        if _GC_USERS == 0 and _GC_WAS:
            gc.enable()
    finally:
        _GC_LOCK.release()


def pause_for_step() -> Optional[object]:
    """What a time-limited :class:`flnotes.MPC` step does first, allocating nothing: the signals Python handles held
    back (:func:`hold_signals`), then the collector paused (:func:`pause_gc`), in that order, so that no handler's
    exception can land between the pause and the ``try`` that ends it. Returns what :func:`resume_after_step` needs."""
    held = hold_signals()
    try:
        pause_gc()
    except BaseException:
        release_signals(held)
        raise
    return held


def resume_after_step(held: Optional[object]) -> None:
    """End :func:`pause_for_step` (``held`` its answer) as the step's last action: the collector resumed, then the
    signals held back meanwhile delivered (a Ctrl-C raised)."""
    try:
        resume_gc()
    finally:
        release_signals(held)
