"""Independent tasks (a video's segments, a plan's runs) on a real local Ray cluster, and without Ray.

The cluster tests start Ray on 127.0.0.1 themselves (two nodes of one CPU: `ray.cluster_utils.Cluster`) and stop
every process they started. A worker killed with SIGKILL mid-segment is retried by Ray and resumes from the
segment's last checkpoint: the models equal, bit for bit, those of a sequential in-process run."""

from __future__ import annotations

import csv
import logging
import os
import pickle
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import warnings
from pathlib import Path

import numba
import pytest
import torch
from scenes import write_panoptic_scene

from stgc.distributed import CONNECT_TIMEOUT_S, Task, TasksFailed, check_reachable, run_tasks
from stgc.errors import DataError, OutputError, StgcError
from stgc.experiment import run_plan
from stgc.experiment.runner import build_train_command, subprocess_runner
from stgc.model import STGModel
from stgc.options import resolve_configs
from stgc.run import Run
from stgc.train.video import train_video

REPO = Path(__file__).resolve().parents[1]
# A tiny video: 2 segments of 2 frames, long enough (in iterations) for a kill to land between checkpoints.
SEGMENT_OVERRIDES = {
    "train.iterations": "200", "train.schedule_scale": "1", "train.checkpoint_every": "25",
    "train.save_iterations": "[200]", "train.threads": "1", "train.progress": "false",
    "train.tensorboard": "false", "train.eval_at_end": "false", "train.eval_every": "0",
    "data.init_source": "random", "data.max_points_per_frame": "200",
}


# ----------------------------------------------------------------------------------- without Ray
def _double(x: int) -> int:
    return 2 * x


def _fail_on_bad_data(path: str) -> None:
    raise DataError(path, "unreadable image")


def test_a_failing_task_is_named_and_the_others_finish_in_process(tmp_path):
    done = []
    tasks = [Task("a", _double, (1,)), Task("b", _fail_on_bad_data, ("frame_7.png",), log_file=tmp_path / "b.log"),
             Task("c", _double, (3,), log_file=tmp_path / "c.log")]
    with pytest.raises(TasksFailed) as failed:
        run_tasks(tasks, use_ray=False, on_done=lambda i, r: done.append((i, r)))
    assert "task failed: DataError: frame_7.png: unreadable image" in (tmp_path / "b.log").read_text()
    assert not (tmp_path / "c.log").exists()  # a task that says nothing leaves no empty log
    assert done == [(0, 2), (2, 6)]
    assert failed.value.failures == {"b": f"frame_7.png: unreadable image (its log: {tmp_path / 'b.log'})"}
    assert "1 of 3 tasks failed; the others finished and are kept" in str(failed.value)
    assert "b: frame_7.png: unreadable image" in str(failed.value)
    assert run_tasks([Task("a", _double, (4,))], use_ray=False) == [8]


def test_a_task_after_others_runs_once_they_have_and_not_after_a_failure_in_process():
    started = []
    tasks = [Task("a", _double, (1,)), Task("bad", _fail_on_bad_data, ("x.png",)),
             Task("after-a", _double, (2,), after=(0,)), Task("after-bad", _double, (3,), after=(1,)),
             Task("declined", _double, (4,), after=(0,))]
    with pytest.raises(TasksFailed) as failed:
        run_tasks(tasks, use_ray=False, start_if=lambda i: started.append(i) or tasks[i].name != "declined")
    assert failed.value.failures["after-bad"] == "not run: bad failed"
    assert started == [0, 1, 2, 4]  # every task whose prerequisites finished, in order (not after-bad)
    with pytest.raises(ValueError, match="only tasks listed before it"):
        run_tasks([Task("a", _double, (1,), after=(1,)), Task("b", _double, (2,))], use_ray=False)


def test_errors_cross_process_boundaries_whole():
    for error in (DataError("x.png", "too small"), OutputError("out.stgc", "disk full"), TasksFailed({"s": "m"}, 2)):
        again = pickle.loads(pickle.dumps(error))
        assert type(again) is type(error) and str(again) == str(error)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_an_unreachable_or_malformed_ray_address_is_a_clear_error(monkeypatch):
    port = _free_port()
    with pytest.raises(StgcError, match=f"127.0.0.1:{port}: cannot reach a Ray cluster there"):
        check_reachable(f"127.0.0.1:{port}")
    # A host that never answers: the probe gives up after CONNECT_TIMEOUT_S ("within seconds", not ray.init's wait).
    asked = []

    def silent_host(address, timeout):
        asked.append(timeout)
        raise TimeoutError("timed out")

    monkeypatch.setattr(socket, "create_connection", silent_host)
    with pytest.raises(StgcError, match=r"10.0.0.9:6379: cannot reach a Ray cluster there \(timed out\)"):
        check_reachable("10.0.0.9:6379")
    assert asked == [CONNECT_TIMEOUT_S] and CONNECT_TIMEOUT_S <= 10
    monkeypatch.undo()
    for bad in ("127.0.0.1", "host:port", ":6379"):
        with pytest.raises(StgcError, match="expected HOST:PORT"):
            check_reachable(bad)
    with pytest.raises(StgcError, match="--no-ray"):
        run_tasks([Task("a", _double, (1,))], use_ray=False, address="127.0.0.1:6379")


# ----------------------------------------------------------------------------------- on Ray
ray = pytest.importorskip("ray", reason="Ray is a dev dependency (the `distributed` extra)")


def _ray_processes(marker: str, ray_tmpdir: str | None = None) -> list[int]:
    """PIDs of live processes whose command line contains `marker` (Ray names its workers ray::<task>), and with
    ray_tmpdir, only those of the Ray started with that RAY_TMPDIR (not another Ray on the machine)."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            if ray_tmpdir is not None and f"RAY_TMPDIR={ray_tmpdir}".encode() not in (entry / "environ").read_bytes():
                continue
        except OSError:
            continue
        if marker in cmdline:
            found.append(int(entry.name))
    return found


def _processes_of(ray_tmpdir: str) -> list[int]:
    """Every live process of the Ray started with this RAY_TMPDIR: its environment or its command line says so."""
    return sorted(set(_ray_processes("", ray_tmpdir)) | set(_ray_processes(ray_tmpdir)))


RAY_AGENTS = ("ray::DashboardAgent", "ray::RuntimeEnvAgent")


def _workers_of(ray_tmpdir: str) -> list[int]:
    """`_processes_of` but Ray's agents: the processes that could still run a task (one read of each command line:
    a process that exits between two reads is gone, not a worker)."""
    alive = [(pid, _cmdline(pid)) for pid in _processes_of(ray_tmpdir)]
    return [pid for pid, command in alive if command != "(gone)" and not command.startswith(RAY_AGENTS)]


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")[:200]
    except OSError:
        return "(gone)"


def _kill_all(ray_tmpdir: str) -> None:
    for pid in _processes_of(ray_tmpdir):
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


@pytest.fixture(scope="module")
def video_scene(tmp_path_factory):
    return write_panoptic_scene(tmp_path_factory.mktemp("rayvideo"), views=5, frames=4, width=32, height=24)


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "stgc.cli", *args]


# First in the module: it starts its own local Ray (in the driver it kills), before the two-node cluster below.
def test_a_killed_driver_leaves_a_video_that_resume_finishes(video_scene, tmp_path):
    """Also: Ray starts workers 15 steps nicer than the driver; the local Ray stgc starts keeps them at the driver's
    priority, so a training task does not starve beside other work (the driver runs 3 steps nicer than this test,
    so that a worker at an absolute niceness would show)."""
    temp = tempfile.mkdtemp(prefix="stgcray", dir="/tmp")
    env = {**os.environ, "RAY_TMPDIR": temp}
    out = tmp_path / "video"
    sets = [arg for key, value in SEGMENT_OVERRIDES.items() for arg in ("--set", f"{key}={value}")]
    # Longer than the other tests' segments, so that a worker cannot finish before it notices the driver is gone.
    sets += ["--set", "train.iterations=600"]
    driver = subprocess.Popen(_cli("train", str(video_scene.root), "--out", str(out), "--segment-frames", "2", *sets),
                              env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
                              preexec_fn=lambda: os.nice(3))
    try:
        segments = [Run(out / "segment_000"), Run(out / "segment_001")]
        deadline = time.monotonic() + 180
        while not any(s.checkpoint_path.is_file() for s in segments) and driver.poll() is None:
            assert time.monotonic() < deadline, "no segment reached its first checkpoint"
            time.sleep(0.02)
        trainers = _ray_processes("ray::segment_", temp)
        assert trainers
        driver_niceness = os.getpriority(os.PRIO_PROCESS, driver.pid)
        if driver_niceness < 19:  # (at 19 Ray's own +15 would give the same)
            niceness = {pid: os.getpriority(os.PRIO_PROCESS, pid) for pid in trainers}
            assert set(niceness.values()) == {driver_niceness}, niceness
        driver.kill()
        driver.wait()
        assert not all(s.training_finished() for s in segments)
        # Ray's workers share the driver's fate: none is left training beside the resumed run (they notice within
        # seconds; a loaded machine can take longer). Ray's two agent processes linger for about a minute before
        # they notice; they train nothing, and the resume does not wait for them.
        deadline = time.monotonic() + 180
        while _workers_of(temp) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert _workers_of(temp) == [], [_cmdline(pid) for pid in _workers_of(temp)]
        # A worker may finish its segment in the seconds before it notices the driver is gone (an idle machine
        # trains this scene fast): what must continue is each segment left checkpointed and unfinished.
        interrupted = [i for i, s in enumerate(segments) if s.checkpoint_path.is_file() and not s.training_finished()]
        assert interrupted, "every segment finished or none checkpointed before the workers stopped"

        resumed = subprocess.run(_cli("train", "--out", str(out), "--resume"), env=env, capture_output=True,
                                 text=True, timeout=300)
        assert resumed.returncode == 0, resumed.stderr[-2000:]
        assert all(s.training_finished() for s in segments)
        starts = [segments[i].read_summary()["started_from_iteration"] for i in interrupted]
        assert min(starts) >= 25  # a checkpointed segment continued, it did not start over
    finally:
        if driver.poll() is None:
            driver.kill()
        _kill_all(temp)
        shutil.rmtree(temp, ignore_errors=True)


def test_the_cli_names_an_unreachable_cluster(video_scene, tmp_path, capsys):
    from stgc.cli import main

    port = _free_port()
    code = main(["train", str(video_scene.root), "--out", str(tmp_path / "v"), "--segment-frames", "2",
                 "--ray-address", f"127.0.0.1:{port}"])
    assert code != 0 and f"127.0.0.1:{port}: cannot reach a Ray cluster" in capsys.readouterr().err
    assert not (tmp_path / "v").exists()  # refused before anything was written
    code = main(["experiment", str(video_scene.root), "--plan", "table2", "--out", str(tmp_path / "x"),
                 "--ray-address", f"127.0.0.1:{port}"])
    assert code != 0 and f"127.0.0.1:{port}: cannot reach a Ray cluster" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
    assert main(["train", str(video_scene.root), "--out", str(tmp_path / "w"), "--ray-address", "auto"]) != 0
    assert "give --segment-frames" in capsys.readouterr().err


@pytest.fixture(scope="module")
def cluster():
    """Two one-CPU Ray nodes on 127.0.0.1 with this test's own temp folder (short: Ray's sockets live there)."""
    from ray.cluster_utils import Cluster

    temp = tempfile.mkdtemp(prefix="stgcray", dir="/tmp")
    env_before = os.environ.get("RAY_TMPDIR")
    os.environ["RAY_TMPDIR"] = temp
    nodes = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False,
                                                          "object_store_memory": 100 * 2**20})
    nodes.add_node(num_cpus=1, object_store_memory=100 * 2**20)
    ray.init(address=nodes.address, logging_level="WARNING", log_to_driver=False)
    # The workers need this module's task functions by value: they cannot import a test module.
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])
    try:
        yield temp  # what tells this cluster's processes from another Ray's
    finally:
        ray.shutdown()
        nodes.shutdown()
        _kill_all(temp)
        if env_before is None:
            os.environ.pop("RAY_TMPDIR", None)
        else:
            os.environ["RAY_TMPDIR"] = env_before
        shutil.rmtree(temp, ignore_errors=True)
        assert _processes_of(temp) == []


@pytest.fixture
def restore_threads():
    """train.threads=1 sets this process's torch and numba threads: give the next tests theirs back."""
    torch_threads, numba_threads = torch.get_num_threads(), numba.get_num_threads()
    yield
    torch.set_num_threads(torch_threads)
    numba.set_num_threads(numba_threads)


def _final_params(run_dir: Path) -> dict[str, torch.Tensor]:
    model = STGModel.load(Run(run_dir).latest_model_dir())
    tensors = {key: p.detach() for key, p in model.params.items()}
    if model.decoder is not None:
        tensors.update({f"decoder.{k}": v for k, v in model.decoder.state_dict().items()})
    return tensors


def _kill_a_worker_mid_run(ray_tmpdir: str, runs: dict[str, Path],
                           timeout_s: float = 300) -> tuple[threading.Thread, list[str]]:
    """A started thread that SIGKILLs the Ray worker (named ray::<task>, of the cluster with `ray_tmpdir`) of the
    first of `runs` (task name -> its run folder) caught between its first checkpoint and its end; the list
    receives that task's name."""
    killed: list[str] = []

    def watch() -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for name, folder in runs.items():
                run, workers = Run(folder), _ray_processes(f"ray::{name}", ray_tmpdir)
                if run.checkpoint_path.is_file() and not run.training_finished() and workers:
                    for pid in workers:
                        os.kill(pid, signal.SIGKILL)
                    killed.append(name)
                    return
            time.sleep(0.02)

    thread = threading.Thread(target=watch, daemon=True)
    thread.start()
    return thread, killed


def test_a_worker_killed_mid_segment_is_retried_and_the_video_is_bit_identical(cluster, video_scene, tmp_path,
                                                                              restore_threads):
    configs = resolve_configs("cpu", {}, {}, SEGMENT_OVERRIDES)
    killer, killed = _kill_a_worker_mid_run(cluster, {name: tmp_path / "ray" / name for name in ("segment_000", "segment_001")})
    train_video(video_scene.root, configs, tmp_path / "ray", 2, use_ray=True)
    killer.join()
    assert killed, "no worker was caught mid-segment"
    victim = Run(tmp_path / "ray" / killed[0])
    summary = victim.read_summary()
    assert summary["finished"] and summary["started_from_iteration"] >= 25  # resumed, not restarted

    train_video(video_scene.root, configs, tmp_path / "inline", 2, use_ray=False)
    for name in ("segment_000", "segment_001"):
        on_ray, inline = _final_params(tmp_path / "ray" / name), _final_params(tmp_path / "inline" / name)
        assert on_ray.keys() == inline.keys()
        for key in inline:
            assert torch.equal(on_ray[key], inline[key]), (name, key)


def _bad_frame_then_fine(index: int) -> int:
    logging.getLogger("stgc.data").info("segment %d: reading its frames", index)
    if index == 1:
        warnings.warn("frame_1.png: 3 of 5 views have no mask", UserWarning, stacklevel=1)
        raise DataError(f"frame_{index}.png", "truncated PNG")
    return index


def _stamp(folder: str, name: str, seconds: float) -> str:
    (Path(folder) / f"{name}.start").write_text(repr(time.time()))
    time.sleep(seconds)
    (Path(folder) / f"{name}.end").write_text(repr(time.time()))
    return name


def test_a_task_starts_when_its_prerequisite_finishes_not_when_every_task_has_on_ray(cluster, tmp_path):
    """Two CPUs: `next` comes after `quick` and starts while `slow` still runs (a plan's fine-tuning runs start
    once their source has trained, beside the other from-scratch runs)."""
    folder = str(tmp_path)
    tasks = [Task("slow", _stamp, (folder, "slow", 6.0)), Task("quick", _stamp, (folder, "quick", 0.5)),
             Task("next", _stamp, (folder, "next", 0.5), after=(1,))]
    assert run_tasks(tasks, use_ray=True, show_progress=False) == ["slow", "quick", "next"]

    def at(name: str, what: str) -> float:
        return float((tmp_path / f"{name}.{what}").read_text())

    assert at("quick", "end") <= at("next", "start") < at("slow", "end")


def test_a_task_failing_on_bad_data_fails_alone_on_ray(cluster, tmp_path):
    """...and what each task said (its log records, its warnings, its failure) is in its own log file: the driver
    does not show a Ray worker's console."""
    done = []
    logs = [tmp_path / f"segment_{i:03d}" / "task.log" for i in range(3)]
    tasks = [Task(f"segment_{i:03d}", _bad_frame_then_fine, (i,), log_file=logs[i]) for i in range(3)]
    with pytest.raises(TasksFailed) as failed:
        run_tasks(tasks, use_ray=True, on_done=lambda i, r: done.append(r), show_progress=False)
    assert sorted(done) == [0, 2]
    assert failed.value.failures == {"segment_001": f"frame_1.png: truncated PNG (its log: {logs[1]})"}
    failed_log = logs[1].read_text()
    assert "segment 1: reading its frames" in failed_log and "3 of 5 views have no mask" in failed_log
    assert "task failed: DataError: frame_1.png: truncated PNG" in failed_log
    assert "segment 0: reading its frames" in logs[0].read_text() and "failed" not in logs[0].read_text()


FAKE_CLI = REPO / "tests" / "experiment" / "fake_stgc_cli.py"
PLAN = """
name = "mini"
baseline = "STG"
[[runs]]
name = "stg"
family = "STG"
overrides = { "compaction.method" = "none" }
[[runs]]
name = "c1"
family = "ST-KNN"
overrides = { "compaction.method" = "st-knn", "compaction.case" = 1, "fake.sleep" = 4 }
[[runs]]
name = "c3"
family = "ST-KNN"
overrides = { "compaction.method" = "st-knn", "compaction.case" = 3 }
"""


def _fake_train_command(data_path, run_dir, preset, overrides, *, resume=False, python=sys.executable):
    """The runner's own command line with the fake trainer of tests/experiment in place of `-m stgc.cli`."""
    return [python, str(FAKE_CLI), *build_train_command(data_path, run_dir, preset, overrides, resume=resume,
                                                       python=python)[3:]]


def _fake_runner(cmd: list[str], log_path: Path) -> int:
    if cmd[1:3] == ["-m", "stgc.cli"]:  # eval and compress commands
        cmd = [cmd[0], str(FAKE_CLI), *cmd[3:]]
    return subprocess_runner(cmd, log_path)


def test_a_plan_on_ray_gives_the_in_process_table_and_survives_a_killed_worker(cluster, tmp_path):
    plan = tmp_path / "mini.toml"
    plan.write_text(PLAN)
    options = dict(codec_qualities=[2], runner=_fake_runner, command_builder=_fake_train_command,
                   check_options=False, log=lambda message: None)
    run_plan("DATA", plan, tmp_path / "inline", use_ray=False, **options)

    killer, killed = _kill_a_worker_mid_run(cluster, {"c1": tmp_path / "ray" / "c1"})
    result = run_plan("DATA", plan, tmp_path / "ray", use_ray=True, **options)
    killer.join()
    assert killed and not result.failed
    inline_table = (tmp_path / "inline" / "results-mini.csv").read_text()
    assert (tmp_path / "ray" / "results-mini.csv").read_text() == inline_table
    # The retry resumed c1; the killed worker's trainer died with it (it would have written a second summary).
    c1_trains = [c for c in (tmp_path / "ray" / "invocations.txt").read_text().splitlines() if "--out" in c
                 and c.split("--out ")[1].split()[0].endswith("/c1")]
    assert len(c1_trains) == 2 and "--resume" in c1_trains[1]
    time.sleep(4.5)  # longer than the killed trainer would have slept
    assert len((tmp_path / "ray" / "invocations.txt").read_text().splitlines()) == len(
        (tmp_path / "inline" / "invocations.txt").read_text().splitlines()) + 1
    # Run again: nothing left to do (every row skipped), the same numbers.
    run_plan("DATA", plan, tmp_path / "ray", use_ray=True, **options)
    again = _rows(tmp_path / "ray" / "results-mini.csv")
    assert {row.pop("status") for row in again} == {"skipped"}
    assert again == [{k: v for k, v in row.items() if k != "status"} for row in _rows(tmp_path / "inline" /
                                                                                       "results-mini.csv")]


def _rows(path: Path) -> list[dict[str, str]]:
    with open(path) as f:
        return list(csv.DictReader(f))


def test_a_task_s_log_file_gets_its_messages_while_a_quiet_console_stays_quiet(tmp_path):
    """The task log needs INFO; lowering the stgc logger for it also un-silenced `stgc -q`'s console handler for as
    long as a segment trained in this process."""
    import io

    from stgc.cli import configure_logging
    from stgc.distributed import run_logged

    logger, warnings_logger = logging.getLogger("stgc"), logging.getLogger("py.warnings")
    saved = [(lg, lg.handlers[:], lg.level, lg.propagate) for lg in (logger, warnings_logger)]
    configure_logging(-1)  # stgc -q
    console = logger.handlers[0]
    shown = io.StringIO()
    console.setStream(shown)  # type: ignore[attr-defined]
    try:
        run_logged(lambda: logging.getLogger("stgc.train").info("initial points: 200"), tmp_path / "task.log")
        assert "initial points" in (tmp_path / "task.log").read_text()
        assert shown.getvalue() == ""
        assert console.level == logging.NOTSET and logger.level == logging.ERROR  # restored after
    finally:
        logging.captureWarnings(False)
        for lg, handlers, level, propagate in saved:
            lg.handlers[:], lg.propagate = handlers, propagate
            lg.setLevel(level)


def test_a_task_s_log_file_leaves_an_application_s_warning_level_root_handler_quiet(tmp_path):
    """A library user's logging.basicConfig(level=WARNING): the stgc logger propagates to root, and lowering it for
    the task log sent every INFO record to the root handler while the task ran; warnings still reach it."""
    import io

    from stgc.distributed import run_logged

    root, logger = logging.getLogger(), logging.getLogger("stgc")
    saved = (root.handlers[:], root.level, logger.handlers[:], logger.level, logger.propagate)
    shown = io.StringIO()
    root.handlers[:], logger.handlers[:], logger.propagate = [logging.StreamHandler(shown)], [], True
    root.setLevel(logging.WARNING)
    logger.setLevel(logging.NOTSET)
    try:
        def task() -> None:
            logging.getLogger("stgc.train").info("initial points: 200")
            logging.getLogger("stgc.train").warning("a camera without a mask")

        run_logged(task, tmp_path / "task.log")
        assert "initial points" in (tmp_path / "task.log").read_text()
        assert "initial points" not in shown.getvalue() and "without a mask" in shown.getvalue()
        assert logger.propagate and logger.level == logging.NOTSET and len(logger.handlers) == 0
    finally:
        root.handlers[:], logger.handlers[:], logger.propagate = saved[0], saved[2], saved[4]
        root.setLevel(saved[1])
        logger.setLevel(saved[3])
