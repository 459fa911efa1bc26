"""The sandbox a submission runs in: bubblewrap (``bwrap``), limits, and the kill at the end.

The submission's kernel and everything it starts run inside ``bwrap`` with new user, PID,
network, IPC, UTS and cgroup namespaces (``--unshare-all``), a new session
(``--new-session``: no terminal to inject into) and a clean environment (``--clearenv``).
The file system it sees is built from nothing: read-only ``/usr`` (the interpreter and
the system libraries), the read-only virtual environment and the ``flnotes`` package
folder, a small ``/tmp`` in memory, its own ``/proc`` (its PID namespace: no process of
the grader or of another submission) and, writable, a fresh copy of its submission
folder mounted at :data:`SUB`; the root and ``/dev`` are read-only, ``/tmp`` and ``/dev/shm``
are small (:attr:`Limits.tmp_mb`). The masters, the bundles, the other submissions and the
reports are not in it.

Limits: per process, the address space (``RLIMIT_AS``), CPU seconds (``RLIMIT_CPU``),
file size (``RLIMIT_FSIZE``) and number of processes (``RLIMIT_NPROC``, counted for the
unprivileged user the sandbox runs as when the grader is root); for the whole tree, a
monitor sums the resident memory of every process in it and the size of the
submission folder and kills the sandbox beyond :attr:`Limits.tree_memory_mb` or
:attr:`Limits.folder_mb`. At the end the sandbox's first process is killed; its PID
namespace dies with it, and with it every process it holds, detached (``setsid``) ones
included.
"""
from __future__ import annotations

import os
import queue
import resource
import shutil
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

__all__ = ["SUB", "Limits", "Sandbox", "SandboxUnavailable", "bwrap_status", "descendants", "selftest"]

#: where the submission's folder appears inside the sandbox
SUB = "/submission"
#: the unprivileged user and group id of the submission inside the sandbox's user namespace
INNER_ID = "65534"
#: the package folder (bound read-only: the notebooks import flnotes)
PACKAGE_DIR = Path(__file__).resolve().parent.parent


class SandboxUnavailable(RuntimeError):
    """bubblewrap is missing or does not work here; grading refuses unless told it may run unsafe."""


@dataclass(frozen=True)
class Limits:
    """What one submission may use.

    Parameters
    ----------
    memory_mb : address space of each process (``RLIMIT_AS``).
    tree_memory_mb : resident memory of all the submission's processes together.
    processes : processes the sandbox's user may have at once beyond those it has already.
    cpu_seconds : CPU time of each process (``RLIMIT_CPU``).
    file_mb : largest file a process may write (``RLIMIT_FSIZE``).
    folder_mb : size of the submission's folder; ``tmp_mb``: size of its ``/tmp``.
    """

    memory_mb: int = 4096
    tree_memory_mb: int = 6144
    processes: int = 64
    cpu_seconds: int = 1200
    file_mb: int = 64
    folder_mb: int = 256
    tmp_mb: int = 256

    def __post_init__(self):
        for k, v in self.__dict__.items():
            if not isinstance(v, int) or v <= 0:
                raise ValueError(f"Limits.{k}={v!r}: give a positive integer")

    def describe(self) -> str:
        return (f"sandbox limits: {self.memory_mb} MB address space per process, {self.tree_memory_mb} MB resident "
                f"for all its processes, {self.processes} processes, {self.cpu_seconds} s CPU per process, "
                f"{self.folder_mb} MB of files")


_STATUS: dict[str, Optional[str]] = {}


def _cgroup_dirs() -> list[tuple[Path, dict[str, str]]]:
    """Where a cgroup (v1 ``pids`` and ``memory`` controllers) for one sandbox can be made, if anywhere."""
    out = []
    try:
        lines = Path("/proc/self/cgroup").read_text().splitlines()
    except OSError:
        return out
    for line in lines:
        _, ctrl, path = line.split(":", 2)
        if ctrl in ("pids", "memory"):
            base = Path("/sys/fs/cgroup", ctrl) / path.lstrip("/")
            if os.access(base, os.W_OK):
                out.append((base, {"pids": "pids.max", "memory": "memory.limit_in_bytes"}[ctrl]))
    return out


def bwrap_status() -> Optional[str]:
    """None when bubblewrap works here (checked once by starting an empty sandbox), else why not."""
    if "bwrap" not in _STATUS:
        exe = shutil.which("bwrap")
        if exe is None:
            _STATUS["bwrap"] = "bubblewrap (bwrap) is not installed (Debian: apt-get install bubblewrap)"
        else:
            try:
                proc = subprocess.run([exe, "--ro-bind", "/", "/", "--unshare-all", "--die-with-parent", "--proc",
                                       "/proc", "--dev", "/dev", "true"], capture_output=True, text=True, timeout=60)
                _STATUS["bwrap"] = None if proc.returncode == 0 else f"bwrap does not work here: {proc.stderr.strip()}"
            except (OSError, subprocess.SubprocessError) as exc:
                _STATUS["bwrap"] = f"bwrap does not work here: {exc}"
    return _STATUS["bwrap"]


def _readonly_roots() -> list[str]:
    """Folders the sandbox sees read-only: the system, the interpreter and its libraries, the package."""
    roots = ["/usr"]
    for p in (sys.base_prefix, sys.prefix, str(PACKAGE_DIR)):
        p = os.path.realpath(p)
        if not any(p == r or p.startswith(r + "/") for r in roots):
            roots.append(p)
    return roots


def bwrap_argv(workdir: str | Path, inner: list[str], env: dict[str, str], limits: Limits) -> list[str]:
    """The ``bwrap`` command line that runs ``inner`` on ``workdir`` (mounted at :data:`SUB`)."""
    argv = [shutil.which("bwrap") or "bwrap", "--unshare-all", "--uid", INNER_ID, "--gid", INNER_ID,
            "--die-with-parent", "--as-pid-1", "--new-session", "--clearenv", "--hostname", "sandbox"]
    # --as-pid-1: the runner (non-dumpable) is the sandbox's first process; no bwrap helper inside holds
    # the channel's pipes where the kernel could open them through /proc/1/fd
    tmp = str(limits.tmp_mb * 1024 * 1024)
    # bwrap mounts in order: the empty /tmp first, so that a venv or package installed under /tmp,
    # bound read-only just after, stays visible on top of it (the other way round the tmpfs hides it)
    argv += ["--proc", "/proc", "--dev", "/dev", "--size", tmp, "--tmpfs", "/dev/shm", "--size", tmp, "--tmpfs", "/tmp"]
    for r in _readonly_roots():
        argv += ["--ro-bind", r, r]
    for link in ("bin", "sbin", "lib", "lib64", "lib32"):  # Debian's merged /usr
        if os.path.islink(f"/{link}") and os.path.exists(f"/usr/{link}"):
            argv += ["--symlink", f"usr/{link}", f"/{link}"]
    for f in ("/etc/ld.so.cache", "/etc/localtime", "/etc/nsswitch.conf", "/etc/fonts"):
        if os.path.exists(f):
            argv += ["--ro-bind", f, f]
    argv += ["--bind", str(workdir), SUB, "--remount-ro", "/dev", "--remount-ro", "/", "--chdir", SUB]
    for k, v in env.items():
        argv += ["--setenv", k, v]
    return argv + ["--"] + inner


def selftest(limits: Limits) -> Optional[str]:
    """None when the grader's own sandbox command line works here, else why not (with bwrap's last words).

    Unlike :func:`bwrap_status`, this runs the very ``bwrap`` command line a submission gets
    (:func:`bwrap_argv`: its mounts, its interpreter) and imports the runner inside it, so an
    install the mounts hide (e.g. under ``/tmp``) is found once per batch, not as a 0 for everyone.
    """
    import tempfile

    why = bwrap_status()
    if why:
        return why
    with tempfile.TemporaryDirectory(prefix="flnotes-selftest-") as workdir:
        inner = [sys.executable, "-c", "import flnotes.grading.runner, nbclient, ipykernel; print('ok')"]
        env = {"PATH": f"{Path(sys.executable).parent}:/usr/bin:/bin", "HOME": SUB, "LANG": "C.UTF-8"}
        try:
            proc = subprocess.run(bwrap_argv(workdir, inner, env, limits), capture_output=True, text=True,
                                  timeout=120, cwd="/", env={"PATH": "/usr/bin:/bin"})
        except (OSError, subprocess.SubprocessError) as exc:
            return f"the sandbox's command line does not work here: {exc}"
    if proc.returncode != 0 or proc.stdout.strip() != "ok":
        tail = " ".join(proc.stderr.strip().splitlines()[-5:])[-600:]
        return (f"the sandbox's command line does not work here (exit {proc.returncode}): {tail or 'no message'}; "
                f"it binds read-only {', '.join(_readonly_roots())}")
    return None


def _children_map() -> dict[int, list[int]]:
    kids: dict[int, list[int]] = {}
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            with open(f"/proc/{d}/stat", "rb") as fh:
                stat = fh.read()
        except OSError:
            continue
        ppid = int(stat[stat.rfind(b")") + 2:].split()[1])
        kids.setdefault(ppid, []).append(int(d))
    return kids


def descendants(pid: int) -> list[int]:
    """Every live process under ``pid`` (found through /proc), ``pid`` excluded."""
    kids, out, todo = _children_map(), [], [pid]
    while todo:
        for c in kids.get(todo.pop(), []):
            out.append(c)
            todo.append(c)
    return out


def _rss_bytes(pids: list[int]) -> int:
    page, total = os.sysconf("SC_PAGE_SIZE"), 0
    for p in pids:
        try:
            with open(f"/proc/{p}/statm") as fh:
                total += int(fh.read().split()[1]) * page
        except (OSError, ValueError, IndexError):
            pass
    return total


def _folder_bytes(path: str, cap_entries: int = 20000) -> int:
    total, n = 0, 0
    for root, dirs, files in os.walk(path):
        for f in files:
            n += 1
            if n > cap_entries:
                return 1 << 62
            try:
                total += os.lstat(os.path.join(root, f)).st_size
            except OSError:
                pass
    return total


def _count_user_processes(uid: int) -> int:
    n = 0
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                if os.stat(f"/proc/{d}").st_uid == uid:
                    n += 1
            except OSError:
                pass
    return n


class Sandbox:
    """One running sandbox: a line-based channel to its first program, its limits, its end.

    ``unsafe=True`` runs the program without bubblewrap (rlimits only): the caller must
    have been told so explicitly, and say so in its report.
    """

    #: largest line accepted from the sandbox (bytes); beyond it the sandbox is killed
    MAX_LINE = 64 * 1024 * 1024
    #: most bytes accepted from one sandbox in all
    MAX_TOTAL = 256 * 1024 * 1024

    def __init__(self, workdir: str | Path, inner: list[str], env: dict[str, str], limits: Limits,
                 *, unsafe: bool = False):
        self.workdir, self.limits, self.unsafe = str(workdir), limits, unsafe
        self.killed = ""  # why the sandbox was killed before its end, if it was
        self.used = 0.0   # seconds spent waiting for the sandbox
        if not unsafe:
            why = bwrap_status()
            if why:
                raise SandboxUnavailable(why)
        nproc = limits.processes + _count_user_processes(os.getuid())
        lim = [(resource.RLIMIT_AS, limits.memory_mb * 1024 * 1024), (resource.RLIMIT_CPU, limits.cpu_seconds),
               (resource.RLIMIT_FSIZE, limits.file_mb * 1024 * 1024), (resource.RLIMIT_CORE, 0)]
        if os.getuid() != 0:  # RLIMIT_NPROC counts every process of the user and does not bind root
            lim.append((resource.RLIMIT_NPROC, nproc))
        self.cgroups: list[Path] = []
        for base, knob in _cgroup_dirs():
            d = base / f"flnotes-grade-{os.getpid()}-{id(self)}"
            try:
                d.mkdir()
                (d / knob).write_text(str(limits.processes if knob == "pids.max"
                                          else limits.tree_memory_mb * 1024 * 1024))
                self.cgroups.append(d)
            except OSError:
                pass
        procs = [str(d / "cgroup.procs") for d in self.cgroups]

        def preexec():  # runs in the child before bwrap starts; everything it starts inherits this
            for what, cap in lim:
                soft, hard = resource.getrlimit(what)
                cap = cap if hard == resource.RLIM_INFINITY else min(cap, hard)
                resource.setrlimit(what, (cap, cap))
            for f in procs:
                with open(f, "w") as fh:
                    fh.write(str(os.getpid()))

        if unsafe:
            env = dict(env, HOME=self.workdir, TMPDIR=self.workdir)
            argv, cwd = inner, self.workdir
        else:
            argv, cwd = bwrap_argv(self.workdir, inner, env, limits), "/"
        self.proc = subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     cwd=cwd, env=env if unsafe else {"PATH": "/usr/bin:/bin"},
                                     start_new_session=True, preexec_fn=preexec)
        self._lines: "queue.Queue[Optional[bytes]]" = queue.Queue()
        self._stderr = bytearray()
        self._stop = threading.Event()
        threading.Thread(target=self._read_stdout, daemon=True).start()
        threading.Thread(target=self._read_stderr, daemon=True).start()
        threading.Thread(target=self._monitor, daemon=True).start()

    # ------------------------------------------------------------------------------
    def _read_stdout(self) -> None:
        buf, total = bytearray(), 0
        out = self.proc.stdout
        while True:
            chunk = out.read1(1 << 16) if hasattr(out, "read1") else out.read(1 << 16)
            if not chunk:
                break
            buf += chunk
            while True:
                i = buf.find(b"\n")
                if i < 0:
                    break
                self._lines.put(bytes(buf[:i]))
                del buf[:i + 1]
            total += len(chunk)
            if len(buf) > self.MAX_LINE or total > self.MAX_TOTAL:
                self.kill("the submission sent more data than the grader accepts")
                break
        self._lines.put(None)

    def _read_stderr(self) -> None:
        while True:
            chunk = self.proc.stderr.read1(1 << 16)
            if not chunk:
                break
            self._stderr += chunk
            if len(self._stderr) > 8192:
                del self._stderr[:-4096]  # keep the tail only

    def _monitor(self) -> None:
        tree_cap, folder_cap = self.limits.tree_memory_mb * 1024 * 1024, self.limits.folder_mb * 1024 * 1024
        n = 0
        while not self._stop.wait(0.2) and self.proc.poll() is None:
            tree = descendants(self.proc.pid) + [self.proc.pid]
            if _rss_bytes(tree) > tree_cap:
                self.kill(f"memory: the submission's processes together exceeded {self.limits.tree_memory_mb} MB")
                return
            if len(tree) > self.limits.processes + 4:
                self.kill(f"processes: the submission ran more than {self.limits.processes} processes at once")
                return
            n += 1
            if n % 5 == 0 and _folder_bytes(self.workdir) > folder_cap:
                self.kill(f"disk: the submission's folder exceeded {self.limits.folder_mb} MB")
                return

    @property
    def stderr_tail(self) -> str:
        return bytes(self._stderr[-2000:]).decode("utf-8", "replace")

    def send(self, line: str) -> None:
        try:
            self.proc.stdin.write(line.encode() + b"\n")
            self.proc.stdin.flush()
        except (OSError, ValueError):
            pass  # the sandbox is gone: the next receive says so

    def receive(self, timeout: float) -> Optional[bytes]:
        """The next line from the sandbox; None when it ended, TimeoutError after ``timeout`` seconds."""
        t0 = time.monotonic()
        try:
            line = self._lines.get(timeout=max(timeout, 0.0))
        except queue.Empty:
            self.used += time.monotonic() - t0
            raise TimeoutError from None
        self.used += time.monotonic() - t0
        return line

    def kill(self, why: str = "") -> None:
        """Kill the sandbox and everything in it (its PID namespace ends with its first process)."""
        if why and not self.killed:
            self.killed = why
        self._stop.set()
        for _ in range(3):
            pids = [self.proc.pid] + descendants(self.proc.pid)
            try:
                os.killpg(self.proc.pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass
            for p in pids:
                try:
                    os.kill(p, signal.SIGKILL)
                except (ProcessLookupError, PermissionError):
                    pass
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                continue
            if not descendants(self.proc.pid):
                break
        for f in (self.proc.stdin, self.proc.stdout, self.proc.stderr):
            try:
                f.close()
            except OSError:
                pass
        for d in self.cgroups:
            for _ in range(50):
                try:
                    d.rmdir()
                    break
                except OSError:
                    time.sleep(0.1)
        self.cgroups = []
