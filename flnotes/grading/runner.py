"""The program that runs inside the sandbox (``python -m flnotes.grading.runner``).

It executes the submission's notebook cell by cell in a Jupyter kernel (inside the same
sandbox), then answers the grader's requests, one JSON line each on its standard input:
``{"op": "names"}`` (the submission's global names: callables and data) and
``{"op": "call", "name": ..., "args": ..., "kwargs": ...}`` (call one student function).
The kernel writes each answer as JSON into the submission's folder; this program reads
it (size-capped) and passes the text on, one line on its standard output, which is the
only way out of the sandbox. The grader decodes it as data (:mod:`flnotes.grading.answers`);
nothing from here is ever executed or imported by the grader. Nothing in this program
is trusted by the grader either: the submission can replace or kill it, and then only
its own answers are lost.
"""
from __future__ import annotations

import json
import os
import sys
import tempfile
import time

#: outputs kept per cell and for the whole notebook (characters); the rest is dropped here
CELL_OUTPUT_CAP = 100_000
NOTEBOOK_OUTPUT_CAP = 1_000_000
#: largest answer file accepted (bytes)
ANSWER_CAP = 32 * 1024 * 1024

KERNEL_HELPER = r'''
def __flnotes_grading__(request_path, answer_path):
    import json, math
    import numpy
    def enc(x, depth=0):
        if depth > 20:
            raise TypeError("nested too deep")
        if x is None or isinstance(x, (bool, str)):
            return x
        if isinstance(x, (int, float, numpy.integer, numpy.floating, numpy.bool_)):
            x = x.item() if hasattr(x, "item") else x
            if isinstance(x, float) and not math.isfinite(x):
                return {"__float__": repr(x)}
            return x
        if isinstance(x, numpy.ndarray):
            if x.dtype.kind not in "biuf":
                raise TypeError(f"an array of dtype {x.dtype}")
            return {"__nd__": enc(x.tolist(), depth + 1), "kind": x.dtype.kind, "shape": list(x.shape)}
        if isinstance(x, tuple):
            return {"__tuple__": [enc(v, depth + 1) for v in x]}
        if isinstance(x, list):
            return [enc(v, depth + 1) for v in x]
        if isinstance(x, dict):
            return {"__dict__": [[enc(k, depth + 1), enc(v, depth + 1)] for k, v in x.items()]}
        raise TypeError(f"an object of type {type(x).__name__}")
    def dec(x):
        if isinstance(x, list):
            return [dec(v) for v in x]
        if isinstance(x, dict):
            if "__nd__" in x:
                kind = {"b": bool, "i": int, "u": int, "f": float}[x["kind"]]
                return numpy.array(dec(x["__nd__"]), dtype=kind).reshape(x["shape"])
            if "__tuple__" in x:
                return tuple(dec(v) for v in x["__tuple__"])
            if "__float__" in x:
                return float(x["__float__"])
            return {dec(k): dec(v) for k, v in x["__dict__"]}
        return x
    with open(request_path) as fh:
        req = json.load(fh)
    g = globals()
    try:
        if req["op"] == "names":
            names = {}
            for k, v in list(g.items()):
                if k.startswith("_") or k in ("In", "Out", "get_ipython", "exit", "quit", "open") or isinstance(v, type):
                    continue
                if type(v).__name__ == "module":
                    names[k] = {"module": True}
                elif callable(v):
                    names[k] = {"callable": True}
                else:  # small data only: a large array of the student's never blocks the list of names
                    try:
                        value = enc(v)
                        if len(json.dumps(value)) <= 100_000:
                            names[k] = {"callable": False, "value": value}
                    except (TypeError, ValueError, RecursionError):
                        pass
            out = {"ok": names}
        else:
            fn = g[req["name"]]
            args, kwargs = dec(req["args"]), dec(req["kwargs"])
            try:
                value = fn(*args, **kwargs)
            except BaseException as exc:
                out = {"raised": f"{type(exc).__name__}: {exc}"[:2000]}
            else:
                try:
                    out = {"ok": enc(value)}
                except TypeError as exc:
                    out = {"raised": f"TypeError: {req['name']} returned {exc}, which cannot be graded "
                                     "(return numbers, arrays, tuples, lists, dicts or strings)"}
    except BaseException as exc:
        out = {"raised": f"{type(exc).__name__}: {exc}"[:2000]}
    with open(answer_path, "w") as fh:
        json.dump(out, fh)
'''


def _client(nb, cell_timeout: int):
    from nbclient import NotebookClient

    class CappedClient(NotebookClient):
        """Keeps at most CELL_OUTPUT_CAP characters of output per cell and NOTEBOOK_OUTPUT_CAP in all."""

        kept_total = 0
        kept_cell: dict = {}

        def output(self, outs, msg, display_id, cell_index):
            size = len(str(msg.get("content", "")))
            used = self.kept_cell.get(cell_index, 0)
            if msg.get("msg_type") != "error" and (used + size > CELL_OUTPUT_CAP
                                                  or self.kept_total + size > NOTEBOOK_OUTPUT_CAP):
                return None
            self.kept_cell[cell_index] = used + size
            self.kept_total += size
            return super().output(outs, msg, display_id, cell_index)

    return CappedClient(nb, timeout=cell_timeout, kernel_name="python3", allow_errors=True, record_timing=False)


def _short(exc: BaseException) -> str:
    lines = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {lines[-1][:200] if lines else ''}"


def _undumpable() -> None:
    """Close this process's ``/proc/<pid>/fd`` to the kernel it starts (same user): ``PR_SET_DUMPABLE`` 0.

    The kernel could otherwise open the grader's channel through ``/proc/<runner>/fd/<n>`` and
    write messages of its own. The kernel (a fresh ``exec``) is dumpable again; only this process is closed.
    The grader still treats every message as untrusted data.
    """
    import ctypes

    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(4, 0, 0, 0, 0) != 0:  # PR_SET_DUMPABLE = 4
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_DUMPABLE, 0) failed")


def main(argv: list[str]) -> int:
    nb_name, cell_timeout = argv[0], int(argv[1])
    _undumpable()
    chan = os.fdopen(os.dup(1), "w", buffering=1)
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)  # the kernel inherits /dev/null, not the grader's channel

    def send(obj) -> None:
        chan.write(json.dumps(obj) + "\n")

    import nbformat
    from nbclient.exceptions import DeadKernelError

    nb = nbformat.read(nb_name, as_version=4)
    client = _client(nb, cell_timeout)
    errors, dead = [], ""
    client.create_kernel_manager()
    env = {k: v for k, v in os.environ.items()}
    client.start_new_kernel(env=env, cwd=os.getcwd())
    client.start_new_kernel_client()
    for i, cell in enumerate(nb.cells):
        if cell.cell_type != "code":
            continue
        try:
            client.execute_cell(cell, i)
        except Exception as exc:  # noqa: BLE001 - a timeout or a dead kernel is reported, the run goes on
            errors.append(f"cell {i}: {_short(exc)}")
            if isinstance(exc, DeadKernelError):
                dead = f"the kernel died while running cell {i}"
                break
            continue
        for o in cell.get("outputs", []):
            if o.get("output_type") == "error":
                first = cell.source.strip().splitlines()[0] if cell.source.strip() else ""
                errors.append(f"cell {i} ({first[:50]!r}): {o.get('ename')}: {str(o.get('evalue'))[:200]}")
    helper = nbformat.v4.new_code_cell(KERNEL_HELPER)
    nb.cells.append(helper)
    if not dead:
        try:
            client.execute_cell(helper, len(nb.cells) - 1)
        except Exception as exc:  # noqa: BLE001
            dead = f"the grader could not talk to the kernel: {_short(exc)}"
    send({"ready": True, "cell_errors": errors[:200], "dead": dead})
    n = 0
    scratch = tempfile.mkdtemp(prefix="flnotes-runner-")
    for line in sys.stdin:
        n += 1
        req_path, ans_path = f"{scratch}/req-{n}.json", f"{scratch}/ans-{n}.json"
        with open(req_path, "w") as fh:
            fh.write(line)
        cell = nbformat.v4.new_code_cell(f"__flnotes_grading__({req_path!r}, {ans_path!r})")
        nb.cells.append(cell)
        t0 = time.monotonic()
        try:
            if dead:
                raise RuntimeError(dead)
            client.execute_cell(cell, len(nb.cells) - 1)
            size = os.stat(ans_path).st_size
            if size > ANSWER_CAP:
                raise ValueError(f"an answer of {size} bytes (at most {ANSWER_CAP})")
            with open(ans_path, encoding="utf-8", errors="replace") as fh:
                text = fh.read(ANSWER_CAP).replace("\n", " ")
        except Exception as exc:  # noqa: BLE001
            if isinstance(exc, DeadKernelError):
                dead = "the kernel died while running a student function"
            text = json.dumps({"raised": _short(exc)})
        for p in (req_path, ans_path):
            try:
                os.unlink(p)
            except OSError:
                pass
        chan.write(f"{n} {time.monotonic() - t0:.3f} {text}\n")
        nb.cells.pop()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
