"""Independent pieces of work (a whole video's segments, an experiment plan's runs) as tasks on Ray.

Each `Task` names a module-level function and its arguments, and the CPUs it needs. `run_tasks` runs them:

- on a local Ray started with this machine's cores (the default), or on an existing cluster (`address`:
  HOST:PORT or "auto"); every node must see the data and the output folder at the same paths, and have stgc
  installed;
- in order, in this process, when Ray is not installed (said once) or not wanted (`use_ray=False`).

Fault tolerance is Ray's task retry: a task whose worker process or node dies is run again (up to `max_retries`
times), and the task functions here are written to continue from what their folder holds (a segment resumes from
its last checkpoint), so a retry redoes at most the work since that checkpoint. An exception raised by the task
itself (bad data) is not retried: it fails that task and the tasks that come `after` it (not run); the others run
to their end and keep their results, and `run_tasks` then raises a `TasksFailed` naming each failed task.

Progress: one bar per task in this process, fed by each task's `progress` callable, which reads the task's output
folder (a shared file system), so workers need no channel back to the driver. Messages: a task with a `log_file`
writes its log records and warnings there (appended, so a retry's follow the failed attempt's), wherever it runs; a
Ray worker's console is not shown by the driver, so that file is where a task's own messages are read.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import logging
import os
import socket
import warnings
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from tqdm import tqdm

from stgc.errors import StgcError

log = logging.getLogger(__name__)

# Seconds between two looks at the tasks' progress (and at finished tasks).
POLL_SECONDS = 1.0
# Seconds to wait for a TCP connection to a cluster given as HOST:PORT before calling it unreachable.
CONNECT_TIMEOUT_S = 5.0
# Local clusters pass only small arguments and results through Ray's object store.
LOCAL_OBJECT_STORE_BYTES = 128 * 2**20
_said_no_ray = False


@dataclasses.dataclass(frozen=True)
class Task:
    """One piece of work: `function(*args)` needing `num_cpus` CPUs. `function` must be importable by name on the
    workers (a module-level function). `progress() -> (done, total)`, run in the driver, feeds its progress bar.
    `log_file`: where the task's log records and warnings are appended. `after`: the tasks (their indices in the
    same `run_tasks` call, all earlier in the list) that must have finished before this one starts."""

    name: str
    function: Callable[..., Any]
    args: tuple[Any, ...] = ()
    num_cpus: int = 1
    progress: Callable[[], tuple[int, int]] | None = None
    log_file: Path | None = None
    after: tuple[int, ...] = ()


LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


def run_logged(function: Callable[..., Any], log_file: Path | None, *args: Any) -> Any:
    """`function(*args)` with stgc's log records (INFO and up) and Python warnings also appended to `log_file`."""
    if log_file is None:
        return function(*args)
    log_file = Path(log_file)
    log_file.parent.mkdir(parents=True, exist_ok=True)
    handler = logging.FileHandler(log_file, encoding="utf-8", delay=True)  # no empty file for a silent task
    handler.setFormatter(logging.Formatter(LOG_FORMAT))
    handler.setLevel(logging.INFO)
    stgc_logger, warnings_logger = logging.getLogger("stgc"), logging.getLogger("py.warnings")
    saved_level, saved_propagate = stgc_logger.level, stgc_logger.propagate
    shown_level = stgc_logger.getEffectiveLevel()
    # Every other handler keeps showing what it showed: the level drops for the log file alone (a fresh Ray worker
    # configured nothing; `stgc -q`, or an application's WARNING-level root handler, must stay quiet while segments
    # train in this process). The logger's own handlers are raised; its ancestors' get what propagation would give
    # them, from the previous level up.
    handler_levels = [(h, h.level) for h in stgc_logger.handlers]
    forward = _Propagate(stgc_logger, shown_level) if saved_propagate and stgc_logger.parent is not None else None
    if shown_level > logging.INFO:
        for existing, level in handler_levels:
            existing.setLevel(max(level, shown_level))
        if forward is not None:
            stgc_logger.propagate = False
            stgc_logger.addHandler(forward)
        stgc_logger.setLevel(logging.INFO)
    stgc_logger.addHandler(handler)
    shown = warnings.showwarning
    try:
        with warnings.catch_warnings():  # restores the caller's warning display, whatever it was
            def show(message: Any, category: Any, filename: str, lineno: int, file: Any = None, line: Any = None) -> None:
                handler.handle(warnings_logger.makeRecord(
                    warnings_logger.name, logging.WARNING, filename, lineno,
                    warnings.formatwarning(message, category, filename, lineno, line).strip(), (), None))
                shown(message, category, filename, lineno, file, line)

            warnings.showwarning = show
            return function(*args)
    except Exception as error:
        logging.getLogger(__name__).error("task failed: %s: %s", type(error).__name__, error)
        raise
    finally:
        stgc_logger.removeHandler(handler)
        handler.close()
        if forward is not None:
            stgc_logger.removeHandler(forward)
        stgc_logger.setLevel(saved_level)
        stgc_logger.propagate = saved_propagate
        for existing, level in handler_levels:
            existing.setLevel(level)


class _Propagate(logging.Handler):
    """What propagation from `logger` would do, for records at `level` and up: each ancestor's handlers, up to the
    first ancestor that does not propagate."""

    def __init__(self, logger: logging.Logger, level: int):
        super().__init__(level)
        self.start = logger.parent

    def emit(self, record: logging.LogRecord) -> None:
        ancestor = self.start
        while ancestor is not None:
            for target in ancestor.handlers:
                if record.levelno >= target.level:
                    target.handle(record)
            ancestor = ancestor.parent if ancestor.propagate else None


class TasksFailed(StgcError):
    """Some tasks failed; the others finished and kept their results. `failures`: {task name: message}."""

    def __init__(self, failures: dict[str, str], total: int):
        self.failures = failures
        self.total = total
        lines = "\n".join(f"  {name}: {message}" for name, message in failures.items())
        kept = "; the others finished and are kept" if total > len(failures) else ""
        super().__init__(f"{len(failures)} of {total} tasks failed{kept}:\n{lines}")

    def __reduce__(self) -> tuple[type, tuple[dict[str, str], int]]:
        return type(self), (self.failures, self.total)


def cpus_for_threads(threads: int) -> int:
    """CPUs a training task asks for: its `train.threads`, or with 0 (leave as is: every core) the whole machine."""
    return threads if threads > 0 else (os.cpu_count() or 1)


def ray_available() -> bool:
    return importlib.util.find_spec("ray") is not None


def run_tasks(tasks: Sequence[Task], *, use_ray: bool = False, address: str | None = None, max_retries: int = 3,
              on_done: Callable[[int, Any], None] | None = None, show_progress: bool = True,
              start_if: Callable[[int], bool] | None = None) -> list[Any]:
    """Run every task and return their results in the order given (None for a task not run). on_done(index, result)
    is called in this process as each one finishes (in finishing order). A task starts as soon as the tasks it
    comes `after` have finished, not when a whole batch has: then `start_if(index)`, in this process, may still
    decline it (it is not run and gets no on_done). A task after one that raised is not run and fails too. Raises
    TasksFailed after all have run if any failed."""
    if not tasks:
        return []
    for index, task in enumerate(tasks):
        if any(not 0 <= earlier < index for earlier in task.after):
            raise ValueError(f"task {task.name!r} comes after {task.after}: only tasks listed before it")
    check_ray_options(use_ray, address)
    if use_ray and not ray_available():
        global _said_no_ray
        if not _said_no_ray:
            log.warning("Ray is not installed: the %d tasks run one after another in this process "
                        "(pip install 'stgc[distributed]' to run them in parallel)", len(tasks))
            _said_no_ray = True
        use_ray = False
    if not use_ray:
        return _run_in_process(tasks, on_done, start_if)
    return _run_on_ray(tasks, address, max_retries, on_done, show_progress, start_if)


def check_ray_options(use_ray: bool, address: str | None) -> None:
    """Refuse Ray options that contradict each other or this machine (call it before writing anything)."""
    if address is not None and not use_ray:
        raise StgcError("--ray-address names a Ray cluster, and --no-ray asks for none: give one of them")
    if address is not None and not ray_available():
        raise StgcError(f"--ray-address {address}: Ray is not installed (pip install 'stgc[distributed]')")


def _failed_before(task: Task, tasks: Sequence[Task], failures: Mapping[str, str]) -> str | None:
    """The name of a task this one comes after that failed, or None."""
    return next((tasks[i].name for i in task.after if tasks[i].name in failures), None)


def _run_in_process(tasks: Sequence[Task], on_done: Callable[[int, Any], None] | None,
                    start_if: Callable[[int], bool] | None) -> list[Any]:
    results: list[Any] = [None] * len(tasks)
    failures: dict[str, str] = {}
    for index, task in enumerate(tasks):  # in list order, every task's `after` has run before it
        failed = _failed_before(task, tasks, failures)
        if failed is not None:
            failures[task.name] = f"not run: {failed} failed"
            continue
        if start_if is not None and not start_if(index):
            continue
        try:
            results[index] = run_logged(task.function, task.log_file, *task.args)
        except StgcError as error:  # the task's own failure (bad data): the others still run
            log.error("%s failed: %s", task.name, error)
            failures[task.name] = _with_log(str(error), task)
            continue
        except Exception as error:  # any other failure is the task's too, as on Ray: its traceback goes to the log
            log.error("%s failed", task.name, exc_info=True)
            failures[task.name] = _with_log(f"{type(error).__name__}: {error}", task)
            continue
        if on_done is not None:
            on_done(index, results[index])
    if failures:
        raise TasksFailed(failures, len(tasks))
    return results


def check_reachable(address: str) -> None:
    """A clear error within seconds when HOST:PORT does not answer (ray.init would wait much longer)."""
    if address == "auto":
        return
    host, sep, port = address.rpartition(":")
    if not sep or not host or not port.isdigit():
        raise StgcError(f"--ray-address {address!r}: expected HOST:PORT (the head node's GCS port, 6379 by "
                        "default) or 'auto'")
    try:
        with socket.create_connection((host, int(port)), timeout=CONNECT_TIMEOUT_S):
            pass
    except OSError as error:
        reason = "timed out" if isinstance(error, TimeoutError) else (error.strerror or str(error))
        raise StgcError(f"--ray-address {address}: cannot reach a Ray cluster there ({reason}); start one with "
                        "`ray start --head` or check the address") from None


def _start_ray(address: str | None) -> bool:
    """Start a local Ray, or connect to the cluster at `address` (its callers probed it with `check_reachable` before
    writing anything); True when this call did either, and so must shut it down."""
    import ray  # optional extra

    if ray.is_initialized():
        return False
    quiet: dict[str, Any] = {"include_dashboard": False, "logging_level": logging.WARNING, "log_to_driver": False}
    if address is None:
        # Ray starts its workers 15 steps nicer than the driver (19 under a driver at 5), so that they yield to its
        # own services; the tasks here are the user's trainings, which then starved beside any other work (one ran at
        # 0.3 it/s beside two trainings at nice 5). Locally they run at the driver's priority.
        ray.init(num_cpus=os.cpu_count() or 1, object_store_memory=LOCAL_OBJECT_STORE_BYTES,
                 _system_config={"worker_niceness": 0}, **quiet)
        return True
    try:
        ray.init(address=address, **quiet)
    except (ConnectionError, RuntimeError, TimeoutError) as error:
        raise StgcError(f"--ray-address {address}: cannot connect ({error})") from None
    return True


def _with_log(message: str, task: Task) -> str:
    return f"{message} (its log: {task.log_file})" if task.log_file is not None else message


def _failure_message(error: Exception) -> str:
    import ray.exceptions  # optional extra

    if isinstance(error, ray.exceptions.RayTaskError):
        cause = error.cause
        if isinstance(cause, StgcError):
            return str(cause)
        return f"{type(cause).__name__}: {cause}"
    return f"{type(error).__name__}: {error}"


def _run_on_ray(tasks: Sequence[Task], address: str | None, max_retries: int,
                on_done: Callable[[int, Any], None] | None, show_progress: bool,
                start_if: Callable[[int], bool] | None) -> list[Any]:
    import ray  # optional extra

    started = _start_ray(address)
    bars: list[Any] = []
    try:
        pending: dict[Any, int] = {}
        # A task asking for more CPUs than any node has would wait forever: it gets the largest node instead.
        largest_node = max((int(node["Resources"].get("CPU", 0)) for node in ray.nodes() if node.get("Alive")),
                           default=1)
        results: list[Any] = [None] * len(tasks)
        failures: dict[str, str] = {}
        done: set[int] = set()
        waiting = list(range(len(tasks)))

        def submit_ready() -> None:
            # In list order: Ray starts queued tasks first come, first served, so the order given is kept among
            # the tasks that can start.
            for index in [i for i in waiting if all(earlier in done for earlier in tasks[i].after)]:
                waiting.remove(index)
                task = tasks[index]
                failed = _failed_before(task, tasks, failures)
                if failed is not None:
                    failures[task.name] = f"not run: {failed} failed"
                    done.add(index)
                    continue
                if start_if is not None and not start_if(index):
                    done.add(index)
                    continue
                cpus = min(task.num_cpus, max(largest_node, 1))
                if cpus < task.num_cpus:
                    log.warning("%s asks for %d CPUs; the largest node has %d: it runs there with %d",
                                task.name, task.num_cpus, largest_node, cpus)
                remote = ray.remote(run_logged).options(num_cpus=cpus, max_retries=max_retries,
                                                        retry_exceptions=False, name=task.name)
                pending[remote.remote(task.function, task.log_file, *task.args)] = index

        log.info("%d tasks on Ray (%s)", len(tasks), address or f"local, {os.cpu_count()} CPUs")
        if show_progress:
            bars = [tqdm(total=1, desc=task.name, unit="it", position=i, dynamic_ncols=True, leave=True)
                    for i, task in enumerate(tasks)]
        submit_ready()
        while pending or waiting:
            ready, _ = ray.wait(list(pending), num_returns=1, timeout=POLL_SECONDS) if pending else ([], [])
            for ref in ready:
                index = pending.pop(ref)
                done.add(index)
                try:
                    results[index] = ray.get(ref)
                except ray.exceptions.RayError as error:
                    failures[tasks[index].name] = _with_log(_failure_message(error), tasks[index])
                    log.error("%s failed: %s", tasks[index].name, failures[tasks[index].name])
                    continue
                if on_done is not None:
                    on_done(index, results[index])
            submit_ready()
            for bar, task in zip(bars, tasks):
                _update_bar(bar, task)
        if failures:
            raise TasksFailed(failures, len(tasks))
        return results
    finally:
        for bar in bars:
            bar.close()
        if started:
            ray.shutdown()


def _update_bar(bar: Any, task: Task) -> None:
    if task.progress is None:
        return
    try:
        done, total = task.progress()
    except (OSError, ValueError):  # a file being written: next time
        return
    if total != bar.total:
        bar.total = total
    if done != bar.n:
        bar.n = done
        bar.refresh()

