"""`stgc` command line. Verbs and their options are generated from the config dataclasses.

Every option of a config section appears as `--<section>.<field>` (see `stgc train --help`), and any of them
can also be given as `--set <section>.<field>=<value>`. Order of precedence: preset < options < --set.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from pathlib import Path
from typing import Any

from stgc import __version__
from stgc.codec import QUALITY_LEVELS, CodecConfig, compress_run, decompress
from stgc.compaction import plot_compaction
from stgc.compaction.config import CASE_WINDOWS, METHODS
from stgc.compaction.criteria import CRITERIA
from stgc.config import (
    EXECUTION_OPTIONS,
    add_config_arguments,
    apply_overrides,
    collect_overrides,
    parse_set_arguments,
    same_place,
    split_sections,
    validate_config,
)
from stgc.data import inspect_text
from stgc.data.preprocess import MODES as PREPROCESS_MODES
from stgc.demo import run_demo
from stgc.errors import StgcError
from stgc.eval import RunEvaluator, evaluate_run, format_eval_table
from stgc.eval.bjontegaard import METHODS as BD_METHODS
from stgc.eval.evaluate import write_video_eval
from stgc.eval.export import EXPORT_FORMATS, export_ply_frames, export_splatv
from stgc.eval.report import report_from_runs
from stgc.eval.video import contact_sheet, load_model_and_dataset, render_still, render_video
from stgc.experiment import run_plan
from stgc.model.layout import VARIANTS
from stgc.options import (
    configs_from_run,
    default_configs,
    refuse_conflicting_flags,
    refuse_unused_compaction_options,
    refuse_unused_feature_options,
    refuse_unused_model_options,
    resolve_configs,
)
from stgc.run import Run
from stgc.train import train
from stgc.train.config import PRESETS, refuse_unused_window_options
from stgc.train.continuation import check_continuable, continuation_configs, start_continuation
from stgc.train.loop import check_rate_aware_window
from stgc.train.video import train_video
from stgc.viewer import serve

# --------------------------------------------------------------------------------------------- config sections
SECTION_TITLES = {
    "data": "data options (stgc.data.DataConfig; defaults shown are the cpu preset's: --preset paper takes every "
            "frame's points, unbounded)",
    "model": "model options (stgc.model.ModelConfig)",
    "train": "training options (stgc.train.TrainConfig; defaults shown are the cpu preset's)",
    "compaction": "compaction options (stgc.compaction.CompactionConfig)",
}


def _resumed_data_path(run: Path, given: str | None, saved: str | None) -> str | None:
    """The data a resumed or fine-tuned run continues on: the saved path; DATA may only name it again, or replace
    it when the saved path is gone (the data moved). Continuing on other data would mix two trainings in one model."""
    if given is None or saved is None:
        return given or saved

    if not same_place(given, saved) and Path(saved).exists():
        raise StgcError(f"{run}: the run trains on {saved}, not {given}; continue it without DATA, or train the "
                        "other data into a new --out")
    return given


def add_ray_arguments(p: argparse.ArgumentParser, unit: str) -> None:
    p.add_argument("--ray-address", metavar="HOST:PORT",
                   help=f"run each {unit} as a task on this Ray cluster ('auto': the one this machine belongs to); "
                        "every node must see the data and --out at the same paths (default: a local Ray with this "
                        f"machine's cores; without Ray installed, the {unit}s run one after another)")
    p.add_argument("--no-ray", action="store_true", help=f"run the {unit}s one after another in this process")


# --------------------------------------------------------------------------------------------- verbs
def cmd_train(args: argparse.Namespace) -> int:
    out = Path(args.out)
    if args.resume and Run(out).has_config():
        given_options = {**{f"{section}.{k}": v for section, opts in collect_overrides(args).items()
                            for k, v in opts.items()}, **parse_set_arguments(args.set)}
        execution = {k: v for k, v in given_options.items() if k in EXECUTION_OPTIONS}
        given = [k for k in ("preset", "variant", "compaction", "case", "criterion") if getattr(args, k, None)]
        given += sorted(k for k in given_options if k not in EXECUTION_OPTIONS)
        if given:
            raise StgcError(f"{out}: a resumed run keeps its saved config.json; drop {', '.join(given)} (only "
                            "options of how it runs may be given: threads, progress, stop_after, ...)")
        saved = configs_from_run(out)
        data_path = _resumed_data_path(out, args.data, saved["data_path"])
        configs = {k: saved[k] for k in ("data", "model", "train", "compaction")}  # stop_after not among them
        for section, values in split_sections(execution, set(configs)).items():
            configs[section] = validate_config(apply_overrides(configs[section], values, section), section)
    else:
        shortcuts: dict[str, dict[str, Any]] = {}
        if args.variant:
            shortcuts.setdefault("model", {})["variant"] = args.variant
        if args.compaction:
            shortcuts.setdefault("compaction", {})["method"] = args.compaction
        if args.case is not None:
            shortcuts.setdefault("compaction", {})["case"] = str(args.case)
        if args.criterion:
            shortcuts.setdefault("compaction", {})["criterion"] = args.criterion
        options, sets = collect_overrides(args), parse_set_arguments(args.set)
        if (args.case is not None or args.criterion) and not args.compaction \
                and "method" not in options.get("compaction", {}) and "compaction.method" not in sets:
            shortcuts["compaction"]["method"] = "st-knn"  # a case or a criterion is ST-KNN's
        configs = resolve_configs(getattr(args, "preset", "cpu"), shortcuts, options, sets)
        refuse_unused_compaction_options(configs["compaction"], [
            *(f"compaction.{key}" for key in {**shortcuts.get("compaction", {}), **options.get("compaction", {})}),
            *sets])
        refuse_unused_window_options(configs["train"], [
            *(f"train.{key}" for key in options.get("train", {})), *sets])
        refuse_unused_model_options(configs["model"], [
            *(f"model.{key}" for key in options.get("model", {})), *sets])
        data_path = args.data
    if data_path is None:
        raise StgcError("no DATA given and the run has no saved data path")
    if args.resume and args.overwrite:
        raise StgcError("--resume continues a run and --overwrite replaces it: give one of them")
    if args.segment_frames is not None or (args.resume and Run(out).is_video()):
        train_video(data_path, configs, out, args.segment_frames, resume=args.resume, overwrite=args.overwrite,
                    evaluator=RunEvaluator(), use_ray=not args.no_ray, ray_address=args.ray_address)
        segments = Run(out).segments()
        unfinished = [s for s in segments if not s.training_finished()]
        if unfinished:  # train.stop_after: no whole video yet to evaluate
            print(f"{out}: {len(unfinished)} of {len(segments)} segments stopped before their end, unfinished "
                  f"(continue them with stgc train --out {out} --resume)")
            return 0
        print(f"whole video written to {out} ({len(segments)} segments)")
        if configs["train"].eval_at_end:
            # A video trained without evaluation and resumed with it has finished segments that never scored
            # themselves: score them now rather than fail on their missing records.
            if all(s.evaluated_finished_model() for s in segments):
                print(format_eval_table(write_video_eval(out)))
            else:
                print(format_eval_table(evaluate_run(out)))
        return 0
    if args.ray_address is not None:
        raise StgcError("--ray-address spreads a whole video's segments over a cluster; give --segment-frames")
    dataset = configs["data"].open(data_path)
    dataset.verify_images(dataset.train, progress=True)  # a corrupt image fails now, not at iteration 14
    # The trainer claims the run folder (stgc.run.prepare_new_run) before it triangulates anything.
    train(
        dataset, configs["data"], configs["model"], configs["train"], configs["compaction"], out, resume=args.resume,
        overwrite=args.overwrite, evaluator=RunEvaluator(),
    )
    if not _said_unfinished(out):
        print(f"run written to {out}")
    record = Run(out).read_eval()
    if record is not None:
        print(format_eval_table(record))
    return 0


def cmd_finetune(args: argparse.Namespace) -> int:
    out, overrides = Path(args.out), parse_set_arguments(args.set)
    check_continuable(args.run)
    configs = continuation_configs(configs_from_run(Path(args.run)), args.run, args.iterations, overrides)
    refuse_unused_feature_options(configs, overrides)  # (EMS options without EMS, ...) as stgc train refuses them
    if configs["train"].densify.is_resolved:  # (as the source saved them) before NEW is written
        check_rate_aware_window(configs["train"], configs["compaction"])
    # The trainer gets an evaluator: a continuation without test views to score is refused before NEW is written.
    data_path = start_continuation(args.run, out, args.iterations, configs, overrides, overwrite=args.overwrite,
                                   data_path=_resumed_data_path(Path(args.run), args.data, configs["data_path"]),
                                   evaluate=True)
    dataset = configs["data"].open(data_path)
    train(dataset, configs["data"], configs["model"], configs["train"], configs["compaction"], out, resume=True,
          evaluator=RunEvaluator())
    if not _said_unfinished(out):
        print(f"run written to {out} ({args.run} + {args.iterations} iterations)")
    record = Run(out).read_eval()
    if record is not None:
        print(format_eval_table(record))
    return 0


def _said_unfinished(out: Path) -> bool:
    """Say so when the run in `out` stopped before its end (train.stop_after); whether it did."""
    run = Run(out)
    if run.training_finished():
        return False
    done, total = run.progress()
    print(f"{out}: stopped at iteration {done} of {total}, unfinished (continue it with stgc train --out {out} "
          "--resume)")
    return True


def cmd_eval(args: argparse.Namespace) -> int:
    record = evaluate_run(args.target, data_path=args.data, measure_fps=not args.no_fps, lpips_net=args.lpips)
    if args.json:
        print(json.dumps(record))
    else:
        print(format_eval_table(record))
    return 0


def cmd_render(args: argparse.Namespace) -> int:
    out = Path(args.out)
    if args.contact_sheet:
        if out.suffix.lower() != ".png" or args.orbit or args.time is not None:
            raise StgcError(f"{out}: a contact sheet is a .png of test cameras at --frames (not --orbit/--time)")

        model, dataset = load_model_and_dataset(args.run, data_path=args.data)
        # Monocular data holds out images at some frames only: the first and last of those.
        shown = list(dataset.frames) if dataset.multiview else sorted({c.frame for c in dataset.test}) or \
            list(dataset.frames)
        frames = args.frames or f"{min(shown)},{max(shown)}"
        contact_sheet(model, dataset, frames, out, cameras=[args.camera] if args.camera else None)
    elif out.suffix.lower() == ".png":
        if args.orbit or args.frames:
            raise StgcError(f"{out}: a .png is one still; use .mp4 or .gif for --orbit or --frames")

        model, dataset = load_model_and_dataset(args.run, data_path=args.data)
        camera = args.camera or str((dataset.test or dataset.train)[0].name)
        render_still(model, camera, 0.0 if args.time is None else args.time, out, dataset=dataset)
    elif out.suffix.lower() in (".mp4", ".gif"):
        if args.time is not None:
            raise StgcError(f"{out}: --time is a still's; a video's frames give its times (use --frames)")
        if args.orbit and (args.camera or args.frames):
            raise StgcError(f"{out}: an --orbit follows its own path over all frames (not --camera/--frames)")
        render_video(args.run, out, camera_name=args.camera, frames=args.frames, orbit=args.orbit,
                     data_path=args.data)
    else:
        raise StgcError(f"{out}: output must end in .png (a still or a contact sheet), .mp4 or .gif (a video)")
    print(f"wrote {out}")
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    if args.format == "splatv":
        if args.frames:
            raise StgcError("--frames applies to ply-frames; a .splatv file holds the whole model over time")
        print(f"wrote {export_splatv(args.source, args.out, data_path=args.data)}")
        return 0
    if Path(args.out).suffix.lower() == ".splatv":
        raise StgcError(f"--out {args.out}: a .splatv file is written with --format splatv ({args.format} writes a "
                        "folder of PLY files)")
    written = export_ply_frames(args.source, args.out, frames=args.frames, data_path=args.data)
    print(f"wrote {len(written)} static 3DGS PLY file(s) to {args.out} (what each holds: {Path(args.out) / 'export.json'})")
    return 0


def cmd_view(args: argparse.Namespace) -> int:
    if not 0 < args.port < 65536:
        raise StgcError(f"--port {args.port}: a TCP port is 1..65535")
    if args.max_side is not None and args.max_side < 16:
        raise StgcError(f"--max-side {args.max_side}: at least 16 pixels")
    serve(args.source, host=args.host, port=args.port, max_side=args.max_side, bitstream=args.bitstream,
          data_path=args.data)
    return 0


def compress_config(args: argparse.Namespace) -> CodecConfig:
    """The codec options `stgc compress` writes with: defaults < --codec.* < --quality < --set."""
    overrides = collect_overrides(args).get("codec", {})
    sets = split_sections(parse_set_arguments(args.set), {"codec"}).get("codec", {})
    if args.quality is not None:
        refuse_conflicting_flags({"codec": {"quality": args.quality}}, [{"codec": overrides}, {"codec": sets}])
        overrides["quality"] = str(args.quality)
    overrides.update(sets)
    return validate_config(apply_overrides(CodecConfig(), overrides, "codec"), "codec")


def cmd_compress(args: argparse.Namespace) -> int:
    result = compress_run(args.run, args.out, config=compress_config(args))
    print(result)
    return 0


def cmd_decompress(args: argparse.Namespace) -> int:
    path = decompress(args.file, args.out, overwrite=args.overwrite)
    print(f"decoded model written to {path}")
    return 0


def cmd_data_inspect(args: argparse.Namespace) -> int:
    print(inspect_text(args.path, format=args.format, decode=args.decode))
    return 0


def cmd_plot(args: argparse.Namespace) -> int:
    run = Path(args.run)
    out = Path(args.out) if args.out else run / "compaction.png"
    plot_compaction(run, out)
    print(f"wrote {out}")
    return 0


def cmd_experiment(args: argparse.Namespace) -> int:
    result = run_plan(
        args.data, args.plan, args.out, preset=args.preset, extra_overrides=args.set or [],
        codec_qualities=sorted(set(args.codec_quality or [])), preprocess=args.preprocess, bd_method=args.bd_method,
        use_ray=not args.no_ray, ray_address=args.ray_address, seeds=args.seeds or (),
    )
    print(result)
    if result.failed:
        print(f"stgc: {len(result.failed)} of {len(result.outcomes)} runs failed", file=sys.stderr)
        return 1
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    result = report_from_runs(args.runs, args.out, baseline=args.baseline, plan=args.plan)
    print(result)
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    return run_demo(Path(args.out), Path(args.data) if args.data else None)


# --------------------------------------------------------------------------------------------- parser
class DefaultsHelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Adds an option's default to its help, unless the help already says it (or there is none to say)."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        help_text = action.help or ""
        if "default" in help_text or action.default in (None, False, argparse.SUPPRESS):
            return help_text
        return super()._get_help_string(action)


def _add_train_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "train",
        help="train an STG model (optionally with ST-KNN compaction) into a run directory",
        description="Train Spacetime Gaussians on DATA into RUN. Presets: cpu (2-core CPU schedule), paper "
        "(official 30k). Any option below can also be given as --set section.field=value.",
        formatter_class=DefaultsHelpFormatter,
    )
    p.add_argument("data", nargs="?", help="dataset directory (any supported layout; see `stgc data inspect`)")
    p.add_argument("--out", required=True, help="run directory to write (or to resume)")

    p.add_argument("--preset", default=argparse.SUPPRESS, choices=sorted(PRESETS),
                   help="training schedule preset (default: cpu; a resumed run keeps its own)")
    p.add_argument("--variant", choices=list(VARIANTS), help="STG variant (shortcut for --model.variant)")
    p.add_argument("--compaction", choices=list(METHODS), help="compaction method (default none)")
    p.add_argument("--case", type=int, choices=sorted(CASE_WINDOWS),
                   help="paper pruning window case (compaction.case); without --compaction: st-knn")
    p.add_argument("--criterion", choices=list(CRITERIA),
                   help="which member of a pair is removed; without --compaction: st-knn")
    p.add_argument("--resume", action="store_true", help="continue RUN from its last checkpoint")
    p.add_argument("--segment-frames", type=int, metavar="N",
                   help="train the video as consecutive N-frame segments (STG: 50), one run each in RUN/segment_<k>/; "
                        "the last segment may be shorter (default: the whole data is one segment)")
    p.add_argument("--overwrite", action="store_true", help="replace the run already in RUN (its files, bitstreams and evaluations are removed)")
    add_ray_arguments(p, "segment")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override any option, e.g. train.iterations=3000")
    try:
        configs = default_configs("cpu")
    except ImportError as exc:  # keep the rest of the CLI usable while a package is broken
        p.epilog = f"(config options unavailable: {exc})"
        configs = {}
    for name, cfg in configs.items():
        add_config_arguments(p, name, cfg, SECTION_TITLES[name])
    p.set_defaults(func=cmd_train)


MODEL_DATA_HELP = ("dataset directory (default: the one recorded in the run; needed for a model without stgc's run "
                   "config, such as an official STG run)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="stgc",
        description="Spacetime Gaussians with spatiotemporal KNN compaction: train, compact, evaluate, compress, report.",
    )

    parser.add_argument("--version", action="version", version=f"stgc {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more detail (DEBUG messages)")
    parser.add_argument("-q", "--quiet", action="count", default=0, help="errors only")
    sub = parser.add_subparsers(dest="verb", metavar="VERB")
    sub.required = True

    _add_train_parser(sub)

    p = sub.add_parser(
        "finetune",
        help="continue a finished run into a new run with changed train.* options (rate-aware fine-tuning)",
        description="Start NEW from RUN's last checkpoint and train ITERATIONS more with RUN's configuration, "
        "changed by --set train.KEY=VALUE (e.g. train.quantization_aware.iterations=1000, "
        "train.quantization_aware.rate_weight=0.001). RUN stays as it is; NEW resumes like any run.",
    )
    p.add_argument("run", help="a finished run directory")
    p.add_argument("--out", required=True, help="the new run directory")
    p.add_argument("--iterations", type=int, required=True, help="iterations to train beyond RUN's")
    p.add_argument("--data", help="dataset directory (default: the one recorded in RUN)")
    p.add_argument("--overwrite", action="store_true", help="replace a run already in NEW")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="change a train.* option")
    p.set_defaults(func=cmd_finetune)

    p = sub.add_parser("eval", help="evaluate a run or a .stgc file on the test views")
    p.add_argument("target", help="run directory or .stgc file (single or whole-video)")
    p.add_argument("--data", help="dataset directory (default: the one recorded in the run)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
    p.add_argument("--no-fps", action="store_true", help="skip the render-speed measurement")
    p.add_argument("--lpips", choices=("alex", "vgg"),
                   help="also LPIPS with this backbone, where it runs without downloading (else its note says why)")
    p.set_defaults(func=cmd_eval)

    p = sub.add_parser("render", help="render a still or a video from a run")
    p.add_argument("run", help="run directory or .stgc file (a whole video's plays across its segments)")
    p.add_argument("--out", required=True, help="FILE.png (still) or FILE.mp4 or FILE.gif (video)")
    p.add_argument("--camera", help="camera name (default: the first test camera)")
    p.add_argument("--orbit", action="store_true", help="smooth camera path through the training cameras")
    p.add_argument("--time", type=float, help="normalised time of a still (default 0)")
    p.add_argument("--frames", help="frame range A:B of a video (default: all), or frames A,B,... of a contact sheet")
    p.add_argument("--contact-sheet", action="store_true",
                   help="FILE.png with one row per test camera (or --camera) and frame: ground truth | render | "
                        "|error| x4 (default frames: the first and the last)")
    p.add_argument("--data", help=MODEL_DATA_HELP)
    p.set_defaults(func=cmd_render)

    p = sub.add_parser("export", help="write a run or .stgc file for other tools (one static 3DGS PLY per frame)")
    p.add_argument("source", help="run directory or .stgc file")
    p.add_argument("--format", choices=EXPORT_FORMATS, default=EXPORT_FORMATS[0],
                   help="ply-frames: one INRIA-layout 3DGS PLY per frame (SuperSplat, gsplat, nerfstudio); splatv: the "
                        "whole model as one file for the splaTV browser viewer")
    p.add_argument("--out", required=True, help="output folder (ply-frames) or FILE.splatv")
    p.add_argument("--frames", help="frame range A:B or frames A,B,... (default: all)")
    p.add_argument("--data", help=MODEL_DATA_HELP)
    p.set_defaults(func=cmd_export)

    p = sub.add_parser("view", help="an interactive viewer in the browser for a run or a .stgc file (viser)")
    p.add_argument("source", help="run directory (single or whole-video) or .stgc file")
    p.add_argument("--host", default="127.0.0.1", help="address to serve on (0.0.0.0: reachable from other machines)")
    p.add_argument("--port", type=int, default=8080, help="TCP port (default 8080)")
    p.add_argument("--max-side", type=int, help="longest side in pixels of a free view's full-resolution render "
                   "(default: the dataset's); a dataset camera always renders at its own size")
    p.add_argument("--bitstream", metavar="NAME.stgc", help="show the run's bitstream of this name (for a whole "
                   "video, each segment's, played as one timeline) instead of its trained model")
    p.add_argument("--data", help=MODEL_DATA_HELP)
    p.set_defaults(func=cmd_view)

    p = sub.add_parser("compress", help="write a trained run as a compact .stgc bitstream")
    p.add_argument("run", help="run directory, iteration directory or .ply; a whole-video run (--segment-frames) is "
                   "written as one .stgc holding every segment's bitstream (docs/stgc-format.md section 9)")
    p.add_argument("--out", required=True, help="output .stgc file")
    p.add_argument("--quality", type=int, help="quality level 1..5 (shortcut for --codec.quality)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a codec option, e.g. "
                   "codec.allocation=ladder")

    add_config_arguments(p, "codec", CodecConfig, "codec options (stgc.codec.CodecConfig)")
    p.set_defaults(func=cmd_compress)

    p = sub.add_parser("decompress", help="decode a .stgc file into an official-layout run directory")
    p.add_argument("file", help=".stgc file (a whole video's restores a whole-video run: a run per segment)")
    p.add_argument("--out", required=True, help="output run directory")
    p.add_argument("--overwrite", action="store_true", help="replace the run already in --out (its files, bitstreams and evaluations are removed; not the input)")
    p.set_defaults(func=cmd_decompress)

    p = sub.add_parser("data", help="dataset tools")
    data_sub = p.add_subparsers(dest="data_verb", metavar="ACTION")
    data_sub.required = True
    q = data_sub.add_parser("inspect", help="print what a dataset directory holds")
    q.add_argument("path", help="dataset directory")
    q.add_argument("--format", default="auto", help="force a reader instead of detecting the layout")
    q.add_argument("--decode", action="store_true", help="decode every image and mask file (finds truncated ones)")
    q.set_defaults(func=cmd_data_inspect)

    p = sub.add_parser("plot", help="plot pruning ratio, loss and Gaussian count of a run over iterations")
    p.add_argument("run", help="run directory")
    p.add_argument("--out", help="PNG path (default RUN/compaction.png)")
    p.set_defaults(func=cmd_plot)

    p = sub.add_parser("experiment", help="run a plan of trainings (paper tables) and write the report")
    p.add_argument("data", help="dataset directory")
    p.add_argument("--plan", required=True, help="table2 | table3 | PLAN.toml")
    p.add_argument("--out", required=True, help="experiment directory (resumable)")

    p.add_argument("--preset", default="cpu", choices=sorted(PRESETS), help="training preset of every run")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override applied to every run")
    p.add_argument("--codec-quality", type=int, action="append", choices=QUALITY_LEVELS,
                   help="also add .stgc rate points at this quality (repeat for several)")
    p.add_argument("--seeds", type=int, nargs="+", metavar="SEED",
                   help="train every run once per seed (train.seed; seed 0 keeps the run's name, seed s is "
                   "<name>-seed<s>); the report gives each run's mean over its seeds, the spread, and the change "
                   "against the baseline seed by seed (a plan may say seeds = [...] itself)")
    add_ray_arguments(p, "run")

    p.add_argument("--preprocess", choices=[m for m in PREPROCESS_MODES if m != "none"],
                   help="point preprocessing of the built-in plans' preprocessed runs (default stg-isolated, what "
                   "the official code does; closest-pairs is the paper's wording)")
    p.add_argument("--bd-method", choices=list(BD_METHODS), default="pchip",
                   help="Bjontegaard interpolation: pchip (piecewise cubic, robust) or cubic (the classic VCEG fit)")
    p.set_defaults(func=cmd_experiment)

    p = sub.add_parser("report", help="tables, RD plots and BD deltas from any set of runs")
    p.add_argument("runs", nargs="+", help="run directories")
    p.add_argument("--out", required=True, help="report directory")
    p.add_argument("--baseline", help="the baseline curve: a method family, or a run (its name or path) whose "
                   "family it is (default: the first run's family)")
    p.add_argument("--plan", help="name the runs as this experiment plan labelled them (a run that several plans "
                   "share keeps each plan's family and label in its experiment.json; default: the first plan's)")
    p.set_defaults(func=cmd_report)

    p = sub.add_parser("demo", help="the whole pipeline on the small embedded scene (what `make demo` runs)")
    p.add_argument("--out", default="demo_out", help="output directory (resumable)")
    p.add_argument("--data", help="scene directory (default: the embedded demo/toys_small)")
    p.set_defaults(func=cmd_demo)
    return parser


def configure_logging(verbosity: int) -> None:
    """stgc's messages go to stderr through `logging` ("stgc: message"): warnings always, what each stage did
    (INFO) by default, its details with -v; -q leaves only errors. Python warnings are routed to the same place."""
    level = {-1: logging.ERROR, 0: logging.INFO}.get(max(-1, min(verbosity, 1)), logging.DEBUG)
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("stgc: %(message)s"))
    logger = logging.getLogger("stgc")
    logger.handlers[:] = [handler]
    logger.setLevel(level)
    logger.propagate = False
    logging.captureWarnings(True)
    warnings_logger = logging.getLogger("py.warnings")
    warnings_logger.handlers[:] = [handler]
    warnings_logger.setLevel(logging.ERROR if verbosity < 0 else logging.WARNING)
    warnings_logger.propagate = False


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    configure_logging(args.verbose - args.quiet)
    try:
        return int(args.func(args) or 0)
    except (StgcError, ValueError) as exc:
        # Configs validate with ValueError naming the field; data/format errors name the file.
        if os.environ.get("STGC_DEBUG"):
            raise
        print(f"stgc: error: {exc}", file=sys.stderr)
        if not isinstance(exc, StgcError):
            print("(set STGC_DEBUG=1 for a traceback)", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("\nstgc: interrupted; run the same command again to continue (a training: stgc train --out RUN "
              "--resume, with no other options than how it runs)", file=sys.stderr)
        return 130
    except OSError as exc:
        # What the verbs' own checks did not foresee (a folder that vanished, a device error): the system's words,
        # which name the file, rather than a traceback.
        if os.environ.get("STGC_DEBUG"):
            raise
        print(f"stgc: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
