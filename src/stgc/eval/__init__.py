"""Evaluation: model size / bitrate / speed accounting, the evaluation driver, Bjøntegaard deltas and paper-style
reports. The image metrics it scores with are `stgc.metrics`, shared with the training loss."""

from stgc.eval.accounting import (
    ModelSize,
    RenderSpeed,
    bitstream_size,
    duration_seconds,
    mbps,
    measure_render_speed,
    mib,
    model_size,
    model_size_of,
    paper_model_bytes,
    size_of_saved_model,
    training_seconds,
)
from stgc.eval.bjontegaard import BDError, bd_psnr, bd_rate
from stgc.eval.evaluate import (
    EvalResult,
    RunEvaluator,
    ViewScore,
    eval_record,
    evaluate,
    evaluate_run,
    format_eval_table,
    open_run_dataset,
    write_eval,
)
from stgc.eval.report import BDResult, Report, ReportRow, make_report, report_from_runs

__all__ = [
    "BDError",
    "BDResult",
    "EvalResult",
    "ModelSize",
    "RenderSpeed",
    "Report",
    "ReportRow",
    "RunEvaluator",
    "ViewScore",
    "bd_psnr",
    "bd_rate",
    "bitstream_size",
    "duration_seconds",
    "eval_record",
    "evaluate",
    "evaluate_run",
    "format_eval_table",
    "make_report",
    "mbps",
    "measure_render_speed",
    "mib",
    "model_size",
    "model_size_of",
    "open_run_dataset",
    "paper_model_bytes",
    "report_from_runs",
    "size_of_saved_model",
    "training_seconds",
    "write_eval",
]
