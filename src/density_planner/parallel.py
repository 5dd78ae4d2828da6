"""One executor for every batch of independent jobs (data generation, benchmark sweeps).

:func:`run_tasks` runs ``fn(task)`` for every task serially, in local worker processes (joblib) or on a Dask
distributed cluster (``scheduler="tcp://host:8786"``, extra ``dask``), and yields ``TaskOutcome`` objects as
tasks finish. Exceptions inside a task are captured in its outcome (with the traceback) instead of aborting the
batch. Each worker limits its own torch threads (one by default), so ``workers`` processes share the cores
without oversubscription. A worker process that dies (killed, out of memory) fails the tasks it was running and
the batch goes on: with joblib the tasks in flight at that moment are reported failed and the rest run in fresh
workers; Dask retries a task on other workers and reports ``KilledWorker`` after its ``allowed-failures``. (Serial
runs execute in this process: nothing can survive its death.)
"""

from __future__ import annotations

import os
import traceback
import warnings
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

__all__ = ["TaskOutcome", "run_tasks", "default_workers", "ForkedCall", "ForkedCallError", "PendingCalls", "end_child",
           "enter_child"]


@dataclass
class TaskOutcome:
    """Result of one task: ``index`` into the task list, ``value`` or ``error`` (a formatted traceback)."""

    index: int
    value: Any = None
    error: str | None = None

    @property
    def ok(self) -> bool:
        return self.error is None


def default_workers() -> int:
    """Number of usable CPU cores."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


class ForkedCallError(RuntimeError):
    """:meth:`ForkedCall.result` of a call that failed; ``cause``: the child's error as one line, or its exit
    code."""

    def __init__(self, cause: str):
        super().__init__(f"the forked call failed ({cause})")
        self.cause = cause


class ForkedCall:
    """``fn(*args)`` computed in a process forked now, while this one goes on: :meth:`result` waits for its value
    (sent back pickled through a pipe). For work that needs no gradient and no GPU and that this process will need
    later, e.g. a scene's road distance field while the planner builds its route seeds. :meth:`start` returns
    ``None`` where ``fork`` does not exist (the caller then computes ``fn`` itself). The child ignores Ctrl-C (the
    parent ends it: :meth:`cancel`, or :meth:`result`) and runs with ``threads`` torch threads if torch is loaded, at
    ``nice`` more niceness (a call with time to spare yields its core to this process's threads)."""

    def __init__(self, proc, conn) -> None:
        self._proc, self._conn = proc, conn

    @classmethod
    def start(cls, fn: Callable[..., Any], *args: Any, threads: int = 1, nice: int = 0) -> ForkedCall | None:
        import multiprocessing as mp
        import sys

        if "fork" not in mp.get_all_start_methods():
            return None
        ctx = mp.get_context("fork")
        here, there = ctx.Pipe(duplex=False)
        for stream in (sys.stdout, sys.stderr):  # the child would print what is still buffered here once more
            stream.flush()
        proc = ctx.Process(target=_forked_call, args=(there, fn, args, threads, nice), daemon=True)
        proc.start()
        there.close()
        return cls(proc, here)

    def result(self) -> Any:
        """The value of ``fn(*args)`` (waits for it); raises :class:`ForkedCallError` naming the child's error or
        exit code. Once only."""
        import pickle

        if self._conn.closed:
            raise RuntimeError("ForkedCall.result() was already taken or the call cancelled")
        try:
            status, value = pickle.loads(self._conn.recv_bytes())
        except EOFError:
            status, value = "error", None
        finally:
            self._conn.close()
        self._proc.join()
        if status != "ok":
            raise ForkedCallError(value or f"exit code {self._proc.exitcode}")
        return value

    def cancel(self) -> None:
        """End the child now (nothing happens once :meth:`result` was taken)."""
        end_child(self._proc, self._conn)


class PendingCalls:
    """:class:`ForkedCall` s started ahead for an owner object (a planning problem, a road scene, a drivable area),
    each under a key (what its value depends on): the later call that needs the value for the same owner and key
    takes it (:meth:`take`) instead of computing it. The one bookkeeping of the command line's helpers (the route
    seeds, the road's distance field). Owners are held weakly and by identity (mutable dataclasses are not
    hashable): a call whose owner is gone, or an entry found under the recycled id of another object, is ended."""

    def __init__(self) -> None:
        self._entries: dict[int, tuple[Any, dict[Any, ForkedCall]]] = {}

    def _calls(self, owner: Any, *, create: bool = False) -> dict[Any, ForkedCall] | None:
        import weakref

        entry = self._entries.get(id(owner))
        if entry is not None and entry[0]() is not owner:  # another object at a recycled id
            self._drop(id(owner))
            entry = None
        if entry is None:
            if not create:
                return None
            key = id(owner)
            entry = (weakref.ref(owner, lambda _ref: self._drop(key)), {})
            self._entries[key] = entry
        return entry[1]

    def _drop(self, key: int) -> None:
        entry = self._entries.pop(key, None)
        if entry is not None:
            for call in entry[1].values():
                call.cancel()

    def __len__(self) -> int:
        """Calls not taken, over all owners."""
        return sum(len(calls) for _, calls in self._entries.values())

    def keys(self, owner: Any) -> list:
        """The keys of ``owner``'s calls not taken yet."""
        calls = self._calls(owner)
        return [] if calls is None else list(calls)

    def start(self, owner: Any, key: Any, fn: Callable[..., Any], *args: Any, nice: int = 0) -> bool:
        """:meth:`ForkedCall.start` ``fn(*args)`` (at ``nice``) under ``owner`` and ``key``; returns whether it
        started (not without ``fork``, nor while a call is pending under that key)."""
        if key in self.keys(owner):
            return False
        call = ForkedCall.start(fn, *args, nice=nice)
        if call is None:
            return False
        calls = self._calls(owner, create=True)
        assert calls is not None
        calls[key] = call
        return True

    def take(self, owner: Any, key: Any) -> ForkedCall | None:
        """``owner``'s call under ``key`` (removed; the caller takes its :meth:`ForkedCall.result`), or ``None``."""
        calls = self._calls(owner)
        if calls is None:
            return None
        call = calls.pop(key, None)
        if not calls:
            self._entries.pop(id(owner), None)
        return call

    def cancel(self, owner: Any) -> None:
        """End every call of ``owner`` not taken."""
        if self._calls(owner) is not None:
            self._drop(id(owner))


def end_child(proc, conn) -> None:
    """End a forked child ``proc`` that talks through ``conn`` (this process's end of their pipe): close ``conn``,
    terminate the child if it still runs, reap it. Nothing happens when ``conn`` is already closed (the child
    answered and was joined)."""
    if conn.closed:
        return
    conn.close()
    if proc.is_alive():
        proc.terminate()
    proc.join()


def enter_child(*, threads: int = 1, nice: int = 0) -> None:
    """The start of a forked helper process (a :class:`ForkedCall`, the ``plan`` command's figures' process): the
    heap inherited from the parent out of the garbage collector's sight (``gc.freeze``: a full collection here scans
    only what the child makes, it scanned the parent's scene and modules, ~0.1 s, and leaves the shared pages
    unwritten), Ctrl-C ignored (the parent ends the child), ``nice`` more niceness, ``threads`` torch threads if torch
    is loaded."""
    import gc
    import os
    import signal
    import sys

    gc.freeze()
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if nice:
        try:
            os.nice(nice)
        except OSError:  # pragma: no cover - not permitted here: the same work at the same priority
            pass
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(threads)


def _forked_call(conn, fn: Callable[..., Any], args: tuple, threads: int, nice: int) -> None:
    """Target of :class:`ForkedCall`: compute, answer ``("ok", value)`` or ``("error", text)``."""
    import pickle

    enter_child(threads=threads, nice=nice)
    try:  # plain pickling (torch's multiprocessing reductions would share memory that dies with this process)
        payload = pickle.dumps(("ok", fn(*args)), protocol=pickle.HIGHEST_PROTOCOL)
    except Exception as exc:  # noqa: BLE001 - the parent raises it as one line
        payload = pickle.dumps(("error", f"{type(exc).__name__}: {exc}"))
    try:
        conn.send_bytes(payload)
    except (BrokenPipeError, OSError):  # the parent cancelled or ended
        pass
    finally:
        conn.close()


class _Call:
    """Picklable wrapper: limit threads, run ``fn(task)``, capture exceptions."""

    def __init__(self, fn: Callable[[Any], Any], threads: int | None):
        self.fn = fn
        self.threads = threads

    def __call__(self, index: int, task: Any) -> TaskOutcome:
        if self.threads is not None:
            import torch

            if torch.get_num_threads() != self.threads:
                torch.set_num_threads(self.threads)
        try:
            return TaskOutcome(index, value=self.fn(task))
        except Exception:  # noqa: BLE001 - every failure is reported in the outcome
            return TaskOutcome(index, error=traceback.format_exc())


def run_tasks(
    fn: Callable[[Any], Any],
    tasks: Sequence[Any] | Iterable[Any],
    *,
    workers: int | None = None,
    scheduler: str | None = None,
    threads_per_worker: int | None = 1,
    progress: bool = False,
    desc: str = "tasks",
) -> Iterator[TaskOutcome]:
    """Run ``fn`` on every task; yields :class:`TaskOutcome` in completion order.

    Args:
        fn: a picklable function (module-level) of one task.
        workers: local processes (default: the number of cores; 1 runs in this process). Ignored with
            ``scheduler``.
        scheduler: address of a Dask distributed scheduler; the tasks run on its workers.
        threads_per_worker: torch threads per worker process (``None`` leaves torch's default).
        progress: show a progress bar over the tasks.
    """
    tasks = list(tasks)
    call = _Call(fn, threads_per_worker)
    from tqdm.auto import tqdm

    bar = tqdm(total=len(tasks), desc=desc, disable=not progress, unit="task")
    try:
        for outcome in _dispatch(call, tasks, workers, scheduler):
            bar.update()
            yield outcome
    finally:
        bar.close()


def _dispatch(call: _Call, tasks: list, workers: int | None, scheduler: str | None) -> Iterator[TaskOutcome]:
    if scheduler:
        yield from _dask(call, tasks, scheduler)
        return
    workers = default_workers() if workers is None else workers
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if workers == 1 or len(tasks) <= 1:
        if call.threads is not None:
            import torch

            previous = torch.get_num_threads()
            try:
                for i, task in enumerate(tasks):
                    yield call(i, task)
            finally:
                torch.set_num_threads(previous)
        else:
            for i, task in enumerate(tasks):
                yield call(i, task)
        return
    yield from _joblib(call, tasks, workers)


class _Marked:
    """Picklable wrapper that touches ``<folder>/<index>`` before running the task (to know which tasks were in
    flight when a worker process died)."""

    def __init__(self, call: _Call, folder: str):
        self.call = call
        self.folder = folder

    def __call__(self, index: int, task: Any) -> TaskOutcome:
        try:
            os.close(os.open(os.path.join(self.folder, str(index)), os.O_CREAT | os.O_WRONLY, 0o600))
        except OSError:  # pragma: no cover - the marker is only a hint
            pass
        return self.call(index, task)


#: loky's warning when it replaces a worker that ended between tasks (joblib/externals/loky/process_executor.py)
_LOKY_REPLACED_WORKER = "A worker stopped while some jobs were given to the executor"


def _joblib(call: _Call, tasks: list, workers: int) -> Iterator[TaskOutcome]:
    """Local worker processes. When a worker process dies (killed, out of memory, ``os._exit``), joblib aborts the
    whole batch: the tasks that had started and not returned are reported as failed, the others run again.

    loky (joblib's executor) ends a worker whose memory grew by more than 300 MB over its size after its first task,
    once the task's result is sent, and starts another, warning "A worker stopped while some jobs were given to the
    executor ... memory leak". A CommonRoad plan's grids (up to 1 GiB) leave such growth in the allocator of a worker
    that planned a large scene; no task is lost or run twice and the new worker starts small, so that warning (once
    or twice per suite sweep) is not shown."""
    import shutil
    import tempfile
    from concurrent.futures.process import BrokenProcessPool

    from joblib import Parallel, delayed

    warnings.filterwarnings("ignore", message=_LOKY_REPLACED_WORKER, category=UserWarning)
    pending = dict(enumerate(tasks))
    folder = tempfile.mkdtemp(prefix="density-planner-tasks-")
    marked = _Marked(call, folder)
    try:
        while pending:
            items = list(pending.items())
            parallel = Parallel(n_jobs=min(workers, len(items)), return_as="generator_unordered")
            try:
                for outcome in parallel(delayed(marked)(i, task) for i, task in items):
                    pending.pop(outcome.index, None)
                    yield outcome
            except BrokenProcessPool as exc:  # joblib's TerminatedWorkerError is a subclass
                started = {int(name) for name in os.listdir(folder) if name.isdigit()} & set(pending)
                lost = sorted(started) or sorted(pending)  # cannot tell which: fail all rather than loop forever
                reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
                for i in lost:
                    pending.pop(i)
                    yield TaskOutcome(i, error=f"WorkerDied: the worker process running this task died "
                                               f"({type(exc).__name__}: {reason})")
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def _dask(call: _Call, tasks: list, scheduler: str) -> Iterator[TaskOutcome]:
    try:
        from distributed import Client, as_completed
    except ImportError:
        from .errors import OptionalDependencyError

        raise OptionalDependencyError("distributed", "dask", "running on a Dask cluster (--scheduler)") from None
    try:
        client = Client(scheduler, timeout="20s")
    except OSError as exc:
        raise ValueError(f"cannot connect to the Dask scheduler at {scheduler!r}: {exc}") from exc
    try:
        futures = client.map(call, range(len(tasks)), tasks, pure=False)
        for future in as_completed(futures):
            try:
                yield future.result()
            except Exception:  # noqa: BLE001 - a lost worker or a task that cannot be unpickled
                index = futures.index(future)
                yield TaskOutcome(index, error=traceback.format_exc())
    finally:
        client.close()
