"""`stgc demo` (what `make demo` runs): the whole pipeline on the small scene shipped in demo/toys_small.

train (uncompacted) -> train with ST-KNN compaction -> evaluate both -> compress both (.stgc) -> evaluate the
bitstreams -> report (Markdown table + RD plot) -> test-view video -> a five-line summary.

It is an experiment plan like the paper tables, so it is resumable: an interrupted demo continues where it
stopped (finished runs are skipped, an unfinished training resumes from its checkpoint).
"""

from __future__ import annotations

import io
import logging
import shlex
import signal
import subprocess
import sys
from pathlib import Path

from stgc.codec import DEFAULT_QUALITY
from stgc.errors import StgcError
from stgc.eval.video import render_video
from stgc.experiment import Plan, RunSpec, run_plan
from stgc.run import Run

_log = logging.getLogger(__name__)
REPO_ROOT = Path(__file__).resolve().parents[2]
DEMO_SCENE = REPO_ROOT / "demo" / "toys_small"

# A short schedule: the `cpu` preset scaled further so that both trainings fit in the 15-minute budget of
# `make demo` on 2 cores (measured in benchmarks/RESULTS.md). Everything else is the cpu preset.
DEMO_OVERRIDES = {
    # The scene has only 10 frames: take the initial points of all of them (30k), not every 3rd as the cpu preset.
    "data.init_frames_every": "1",
    "train.iterations": "1500",
    "train.schedule_scale": "0.05",
    "train.checkpoint_every": "100",
    "train.log_every": "20",
}


def demo_plan() -> Plan:
    return Plan(
        name="demo",
        runs=(
            RunSpec("stg", {"data.preprocess": "none", "compaction.method": "none"}, "STG", "Trained model"),
            RunSpec(
                "st-knn",
                {"data.preprocess": "none", "compaction.method": "st-knn", "compaction.case": "2",
                 "compaction.criterion": "timestamp"},
                "ST-KNN (proposed)",
                "Case 2",
            ),
        ),
        baseline="STG",
        title="stgc demo: STG vs ST-KNN compaction vs .stgc bitstream (toys_small)",
    )


def tee_runner(cmd: list[str], log_path: Path) -> int:
    """Run a pipeline step showing its progress on the terminal while keeping a log."""
    log_path.parent.mkdir(parents=True, exist_ok=True)
    with open(log_path, "a") as log:
        log.write(f"\n$ {' '.join(cmd)}\n")
        log.flush()
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        output = proc.stdout
        assert isinstance(output, io.BufferedReader)
        try:
            for chunk in iter(lambda: output.read1(4096), b""):
                sys.stdout.buffer.write(chunk)
                sys.stdout.flush()
                log.write(chunk.decode(errors="replace"))
            return proc.wait()
        finally:
            # Interrupted (Ctrl-C, kill): stop the step too, so a re-run never finds it still writing the run.
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
                try:
                    proc.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()


def _fmt(record: dict | None, key: str, spec: str) -> str:
    value = (record or {}).get(key)
    return format(value, spec) if isinstance(value, (int, float)) else "-"


def run_demo(out_dir: Path, data: Path | None = None) -> int:
    data = Path(data) if data is not None else DEMO_SCENE
    if not data.is_dir():
        raise StgcError(f"{data}: demo scene not found (it ships in the repository under demo/toys_small)")
    out_dir = Path(out_dir)
    print(f"stgc demo: scene {data}, output {out_dir} (re-run to resume)", flush=True)
    result = run_plan(
        data, demo_plan(), out_dir, preset="cpu", extra_overrides=DEMO_OVERRIDES,
        codec_qualities=[DEFAULT_QUALITY], runner=tee_runner,
    )
    if result.failed:
        for o in result.failed:
            _log.error("demo: %s failed: %s", o.name, o.message)
        if any(o.stale for o in result.failed):
            # The demo's folder is the demo's own, but it may hold results: name the remedy, delete nothing.
            _log.error("demo: %s holds a demo made with other options or data (an older stgc's defaults, or another "
                       "scene); remove it (rm -rf %s) and run the demo again", out_dir, shlex.quote(str(out_dir)))
        return 1
    by_name = {o.name: o for o in result.outcomes}
    compacted_run = out_dir / "st-knn"
    video = out_dir / "test_view.mp4"
    trained = Run(compacted_run).summary_path
    if not video.is_file() or (trained.is_file() and video.stat().st_mtime < trained.stat().st_mtime):
        render_video(compacted_run, video)  # again after a new training: the video must show what is reported

    rows = [
        ("uncompacted", by_name.get("stg")),
        ("ST-KNN compacted", by_name.get("st-knn")),
        (f"compacted + .stgc q{DEFAULT_QUALITY}", by_name.get(f"st-knn-q{DEFAULT_QUALITY}")),
    ]
    print()
    if result.report is not None:
        print(f"report:     {_shown(result.report.markdown)}")
        print(f"RD plot:    {_shown(result.report.plot_png)}")
    print(f"video:      {_shown(video)}")
    print(f"bitstream:  {_shown(compacted_run / f'model_q{DEFAULT_QUALITY}.stgc')}")
    print()
    print(f"{'model':<26} {'Gaussians':>10} {'MiB':>8} {'Mbps':>9} {'PSNR dB':>8}")
    for label, outcome in rows:
        rec = outcome.record if outcome else None
        print(
            f"{label:<26} {_fmt(rec, 'num_gaussians', 'd'):>10} {_fmt(rec, 'size_mb', '.3f'):>8} "
            f"{_fmt(rec, 'mbps', '.2f'):>9} {_fmt(rec, 'psnr', '.2f'):>8}"
        )
    return 0


def _shown(path: Path | None) -> str:
    """`path` as the user would type it from here: relative to the working directory when inside it."""
    if path is None:
        return "-"
    try:
        return str(Path(path).resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)
