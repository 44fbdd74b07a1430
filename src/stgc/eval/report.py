"""Paper-style reports: a Markdown table laid out like the paper's Table 2/3, rate-distortion plots
(Mbps vs PSNR, one curve per method family, PNG + SVG) and Bjøntegaard deltas of every curve against a baseline.

A report is made from rows (`ReportRow`), either given directly (`make_report`) or read from run directories
(`report_from_runs`: each run's eval.json, config.json and, when the experiment runner wrote it,
experiment.json naming the run's family and label). Rows scored on different test sets (data, test cameras,
frames, downscale) never share a curve, a BD delta or the change against the reference (`split_test_sets`).
"""

from __future__ import annotations

import logging
import math
import re
import string
import textwrap
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from stgc.config import same_place
from stgc.errors import DataError, FormatError
from stgc.eval.bjontegaard import BDError, Method, bd_psnr, bd_rate
from stgc.fileio import atomic_open, atomic_path, read_json_object, write_json
from stgc.metrics.image import PSNR_CEILING_DB
from stgc.run import Run

log = logging.getLogger(__name__)

SIZE_NOTE = ("Size (MB) is MiB (2^20 bytes) of raw float32 PLY rows (152 B per full Gaussian, normals included) "
             "plus float32 decoder weights, as in the paper; for .stgc rows it is the file size. "
             "Mbps = 10^6 bits per second of video the model covers (= MiB x 8.388608 for a 1-s model).")


@dataclass
class ReportRow:
    """One rate point. `family` groups points into one RD curve; `name` labels the point."""

    name: str
    family: str
    mbps: float | None
    psnr: float | None
    num_gaussians: int | None = None
    size_mb: float | None = None
    ssim: float | None = None
    lpips: float | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def from_mapping(cls, m: Mapping[str, Any]) -> ReportRow:
        known = {"name", "family", "mbps", "psnr", "num_gaussians", "size_mb", "ssim", "lpips"}
        if "name" not in m:
            raise ValueError(f"report row without a name: {dict(m)}")
        return cls(
            name=str(m["name"]),
            family=str(m.get("family") or m["name"]),
            mbps=_num(m.get("mbps")),
            psnr=_psnr(m.get("psnr")),
            num_gaussians=None if m.get("num_gaussians") in (None, "") else int(float(m["num_gaussians"])),
            size_mb=_num(m.get("size_mb")),
            ssim=_num(m.get("ssim")),
            lpips=_num(m.get("lpips")),
            extra={k: v for k, v in m.items() if k not in known and k != "extra"} | dict(m.get("extra") or {}),
        )


def _num(x: Any) -> float | None:
    if x is None or x == "":
        return None
    v = float(x)
    return v if math.isfinite(v) else None


def _psnr(x: Any) -> float | None:
    """A row's PSNR; an exact render (+inf) counts at the ceiling the evaluation itself uses, so that the best
    point of a curve is not the one left out."""
    if x is not None and x != "" and float(x) == math.inf:
        return PSNR_CEILING_DB
    return _num(x)


@dataclass
class BDResult:
    family: str
    baseline: str
    points: int
    bd_rate: float | None
    bd_psnr: float | None
    note: str = ""


@dataclass
class Report:
    out_dir: Path
    markdown: Path
    plot_png: Path | None
    plot_svg: Path | None
    json_path: Path
    rows: list[ReportRow]
    bd: list[BDResult]
    baseline: str | None

    def __str__(self) -> str:
        files = [self.markdown, self.plot_png, self.plot_svg, self.json_path]
        return "report written:\n" + "\n".join(f"  {p}" for p in files if p is not None)


# What names the test set a row was scored on: the data folder, the test cameras, the frames and the images'
# downscale (`stgc.eval.evaluate.dataset_identity`; an eval.json lists its cameras and frames). Rates and PSNRs
# of two test sets are not points of one curve, and BD deltas between them measure the test sets, not the methods.
TEST_SET_FIELDS = ("data", "cameras", "frames", "downscale")


def _identity(row: ReportRow) -> dict[str, Any]:
    """The test set a row names, each field None where the row does not say (records written before they did,
    rows given directly)."""
    out: dict[str, Any] = {}
    for key in TEST_SET_FIELDS:
        value = row.extra.get(key)
        if value is None or value == "" or value == []:
            out[key] = None
        elif key in ("cameras", "frames"):
            out[key] = tuple(str(v) for v in value) if isinstance(value, (list, tuple)) else (str(value),)
        elif key == "downscale":
            try:
                out[key] = float(value)
            except (TypeError, ValueError):
                out[key] = str(value)
        else:
            out[key] = str(value)
    return out


def _same_field(key: str, first: Any, second: Any) -> bool:
    if key != "data":
        return bool(first == second)
    if same_place(first, second):
        return True
    # A data folder that is gone (moved since that evaluation) can only be told by its name.
    return (not Path(first).exists() or not Path(second).exists()) and Path(first).name == Path(second).name


def same_test_set(first: ReportRow, second: ReportRow) -> bool:
    """Whether two rows were scored on one test set, as far as both say (a field a row does not name agrees with
    any; a data folder by its place, or by its name where it is gone)."""
    a, b = _identity(first), _identity(second)
    return all(a[k] is None or b[k] is None or _same_field(k, a[k], b[k]) for k in TEST_SET_FIELDS)


def _test_sets(rows: Sequence[ReportRow]) -> tuple[list[int], list[dict[str, Any]]]:
    """(the test set of each row, as an index into the list of test sets; that list, in order of first appearance).
    A field a row does not name agrees with any: such a row joins the first test set the fields it names allow."""
    sets: list[dict[str, Any]] = []
    groups = []
    for row in rows:
        ident = _identity(row)
        for index, known in enumerate(sets):
            if all(ident[k] is None or known[k] is None or _same_field(k, ident[k], known[k]) for k in TEST_SET_FIELDS):
                known.update({k: v for k, v in ident.items() if known[k] is None})
                groups.append(index)
                break
        else:
            sets.append(dict(ident))
            groups.append(len(sets) - 1)
    return groups, sets


def _set_label(index: int) -> str:
    return string.ascii_uppercase[index] if index < len(string.ascii_uppercase) else str(index + 1)


def _families(rows: Sequence[ReportRow]) -> dict[str, list[ReportRow]]:
    """The rows by curve: by family, and a family scored on several test sets as one curve per test set (what
    `split_test_sets` names them; there each family is already of one)."""
    groups, _ = _test_sets(rows)
    first: dict[str, int] = {}
    mixed = set()
    for r, g in zip(rows, groups):
        if first.setdefault(r.family, g) != g:
            mixed.add(r.family)
    out: dict[str, list[ReportRow]] = {}
    for r, g in zip(rows, groups):
        out.setdefault(f"{r.family} [test set {_set_label(g)}]" if r.family in mixed else r.family, []).append(r)
    return out


def split_test_sets(rows: Sequence[ReportRow], baseline: str | None) -> tuple[list[ReportRow], dict[str, dict]]:
    """The rows with each family split by the test set its rows were scored on, and {label: test set} of the
    test sets: (the rows as they are, {}) where all share one. The baseline family's test set (else the first
    row's) is test set A, whose rows keep their family; a row of another test set X joins the family
    "<family> [test set X]", a curve of its own that is compared with no curve of another test set."""
    groups, sets = _test_sets(rows)
    if len(sets) < 2:
        return list(rows), {}
    reference = next((g for r, g in zip(rows, groups) if r.family == baseline), groups[0])
    order = [reference] + [g for g in range(len(sets)) if g != reference]
    label = {g: _set_label(k) for k, g in enumerate(order)}
    split = [replace(r, family=r.family if g == reference else f"{r.family} [test set {label[g]}]",
                     extra={**r.extra, "test_set": label[g]}) for r, g in zip(rows, groups)]
    return split, {label[g]: {k: list(v) if isinstance(v, tuple) else v for k, v in sets[g].items()} for g in order}


def describe_test_set(test_set: Mapping[str, Any]) -> str:
    """One line naming a test set (`split_test_sets`'s values)."""
    frames = test_set.get("frames")
    if frames and all(str(f).lstrip("-").isdigit() for f in frames):
        numbers = sorted(int(f) for f in frames)
        shown = f"{numbers[0]}-{numbers[-1]}" if numbers == list(range(numbers[0], numbers[-1] + 1)) else \
            ", ".join(map(str, numbers))
    else:
        shown = ", ".join(map(str, frames)) if frames else "?"
    cameras = test_set.get("cameras")
    downscale = test_set.get("downscale")
    scale = "?" if downscale is None else format(downscale, "g") if isinstance(downscale, float) else str(downscale)
    return (f"data {test_set.get('data') or '?'}, test camera(s) {', '.join(map(str, cameras)) if cameras else '?'}, "
            f"frames {shown}, downscale {scale}")


def _group_of(rows: Sequence[ReportRow]) -> dict[int, int]:
    """{id(row): index of its test set} (`_test_sets`)."""
    groups, _ = _test_sets(rows)
    return {id(r): g for r, g in zip(rows, groups)}


def _curve(rows: Sequence[ReportRow]) -> list[ReportRow]:
    return sorted((r for r in rows if r.mbps is not None and r.psnr is not None and r.mbps > 0),
                  key=lambda r: r.mbps)  # type: ignore[arg-type, return-value]


def _front(curve: Sequence[ReportRow]) -> list[ReportRow]:
    """The points of a rate-sorted curve that no other point beats: each has a higher PSNR than every point of
    lower or equal rate. A family that gathers several runs at several codec qualities is a cloud, not a curve;
    interpolating through its dominated points zigzags, and the BD deltas then depend on points the family would
    never choose."""
    front: list[ReportRow] = []
    for r in curve:
        while (front and float(front[-1].mbps) == float(r.mbps)  # type: ignore[arg-type]
               and float(front[-1].psnr) <= float(r.psnr)):  # type: ignore[arg-type]
            front.pop()
        if not front or float(r.psnr) > float(front[-1].psnr):  # type: ignore[arg-type]
            front.append(r)
    return front


CODEC_SUFFIX = " + codec"  # a family's codec points (its runs' .stgc files) are the family of this name
RATE_POINTS = 4  # rp01..rp04, as the MPEG Gaussian-splat-coding test conditions name a curve's points


def rate_points(rows: Sequence[ReportRow]) -> dict[int, str]:
    """{id(row): "rp01".."rp04"} for each curve's points from its lowest rate up (MPEG's numbering: rp01 is the
    lowest rate). The curve is the family's Pareto front (`_front`), as the BD deltas and the plot's line see it: a
    dominated point names no rate point. A curve with more than four points names four of them, spread evenly over
    its log rate: the lowest, the highest, and the points nearest one and two thirds of the way between."""
    names: dict[int, str] = {}
    for members in _families(rows).values():
        curve = _front(_curve(members))
        if len(curve) > RATE_POINTS:
            logs = np.log([float(r.mbps) for r in curve])  # type: ignore[arg-type]
            picked: list[int] = []
            for target in np.linspace(logs[0], logs[-1], RATE_POINTS):
                free = [i for i in range(len(curve)) if i not in picked]
                picked.append(min(free, key=lambda i: abs(logs[i] - target)))
            curve = [curve[i] for i in sorted(picked)]
        names.update({id(r): f"rp{k + 1:02d}" for k, r in enumerate(curve)})
    return names


def resolve_baseline(rows: Sequence[ReportRow], baseline: str | None) -> str | None:
    """The baseline family: `baseline` may name a family or a row (run); default: the first row's family."""
    if not rows:
        return None
    if baseline is None:
        return rows[0].family
    families = list(dict.fromkeys(r.family for r in rows))  # as given: a family of two test sets is one name here
    if baseline in families:
        return baseline
    for r in rows:  # a run by name, or by the path `stgc report` was given it as
        run_dir = str(r.extra.get("run_dir", ""))
        if baseline in (r.name, r.extra.get("run"), Path(run_dir).name) or (
                run_dir and Path(baseline).exists() and same_place(baseline, run_dir)):
            return r.family
    raise ValueError(f"baseline {baseline!r} is neither a method family ({', '.join(families)}) nor a run name")


def bd_table(rows: Sequence[ReportRow], baseline: str | None, method: Method = "pchip") -> list[BDResult]:
    """BD-rate / BD-PSNR of every other family's curve against the baseline family's curve, each curve reduced to
    its Pareto front (`_front`; the note says how many points were left out)."""
    if baseline is None:
        return []
    families = _families(rows)
    base_all = _curve(families.get(baseline, []))
    base = _front(base_all)
    group = _group_of(rows)
    base_sets = {group[id(r)] for r in families.get(baseline, [])}
    results = []
    for name, members in families.items():
        if name == baseline:
            continue
        curve_all = _curve(members)
        curve = _front(curve_all)
        result = BDResult(name, baseline, len(curve), None, None)
        if base_sets and {group[id(r)] for r in members} != base_sets:
            result.note = (f"n/a: scored on another test set ({_sets_named(members)}) than the baseline "
                           f"({_sets_named(families[baseline])}); PSNRs of different test views are not comparable")
            results.append(result)
            continue
        dropped = [f"{n} dominated point(s) of {what} left out" for n, what in
                   ((len(curve_all) - len(curve), "this curve"), (len(base_all) - len(base), "the baseline")) if n]
        dropped += [f"{n} point(s) of {what} without a rate and a finite PSNR left out" for n, what in
                    ((len(members) - len(curve_all), "this curve"),
                     (len(families.get(baseline, [])) - len(base_all), "the baseline")) if n]
        try:
            if len(base) < 2 or len(curve) < 2:
                raise BDError(f"needs >= 2 rate points per curve (baseline {len(base)}, this {len(curve)})")
            args = ([r.mbps for r in base], [r.psnr for r in base], [r.mbps for r in curve], [r.psnr for r in curve])
            # The shared ranges the deltas average over: a value over a sliver of PSNR says little, and the reader
            # should see that it is one.
            shared = []
            try:
                result.bd_rate = bd_rate(*args, method=method)  # type: ignore[arg-type]
                lo, hi = _shared([r.psnr for r in base], [r.psnr for r in curve])
                shared.append(f"BD-rate over {lo:.2f}-{hi:.2f} dB ({hi - lo:.2f} dB shared)")
            except BDError as exc:
                shared.append(f"BD-rate n/a: {exc}")
            try:
                result.bd_psnr = bd_psnr(*args, method=method)  # type: ignore[arg-type]
                lo, hi = _shared([r.mbps for r in base], [r.mbps for r in curve])
                shared.append(f"BD-PSNR over {lo:.3g}-{hi:.3g} Mbps")
            except BDError as exc:
                shared.append(f"BD-PSNR n/a: {exc}")
            result.note = "; ".join(shared)
        except BDError as exc:
            result.note = f"n/a: {exc}"
        result.note = "; ".join([*dropped, *([result.note] if result.note else [])])
        results.append(result)
    return results


def _sets_named(members: Sequence[ReportRow]) -> str:
    labels = sorted({str(r.extra.get("test_set") or "?") for r in members})
    return "test set " + ", ".join(labels)


def _shared(first: Sequence[Any], second: Sequence[Any]) -> tuple[float, float]:
    """The range two curves share on one axis (rate or PSNR)."""
    return max(min(map(float, first)), min(map(float, second))), min(max(map(float, first)), max(map(float, second)))


def _f(x: float | None, fmt: str) -> str:
    return "–" if x is None else format(x, fmt)


def markdown_table(rows: Sequence[ReportRow], baseline: str | None, bd: Sequence[BDResult],
                   title: str = "Rate-distortion results", bd_method: str = "pchip") -> str:
    """The paper's Table 2 layout: method | setting | # Gaussians | size (MB) | Mbps | PSNR (dB) | SSIM,
    then change against the baseline's highest-rate point on its Pareto front (its best), then the BD deltas."""
    show_lpips = any(r.lpips is not None for r in rows)
    show_yuv = any(_num(r.extra.get("psnr_yuv")) is not None for r in rows)
    points = rate_points(rows)
    ref = _front(_curve(_families(rows).get(baseline, [])))[-1:] if baseline else []
    ref_row = ref[0] if ref else None
    group = _group_of(rows)
    elsewhere = 0  # rows of another test set than the reference's: their change against it means nothing
    head = ["Method", "Setting", "RP", "# Gaussians", "Size (MB)", "Mbps", "PSNR (dB)"]
    head += ["YUV-PSNR (dB)"] if show_yuv else []
    head += ["SSIM"]
    head += ["LPIPS"] if show_lpips else []
    head += ["Rate vs ref.", "ΔPSNR vs ref. (dB)"] if ref_row else []
    lines = [f"## {title}", "", "| " + " | ".join(head) + " |",
             "|" + "|".join(["---", "---"] + ["---:"] * (len(head) - 2)) + "|"]
    for family, members in _families(rows).items():
        for i, r in enumerate(members):
            cells = [family if i == 0 else "", r.name, points.get(id(r), ""),
                     "–" if r.num_gaussians is None else f"{r.num_gaussians:,}",
                     _f(r.size_mb, ".2f"), _f(r.mbps, ".2f"), _f(r.psnr, ".2f")]
            if show_yuv:
                cells.append(_f(_num(r.extra.get("psnr_yuv")), ".2f"))
            cells.append(_f(r.ssim, ".4f"))
            if show_lpips:
                cells.append(_f(r.lpips, ".4f"))
            if ref_row and group[id(r)] != group[id(ref_row)]:
                cells += ["–", "–"]
                elsewhere += 1
            elif ref_row:
                ratio = (r.mbps / ref_row.mbps - 1) * 100 if r.mbps and ref_row.mbps else None
                cells.append("–" if ratio is None else f"{ratio:+.1f} %")
                cells.append("–" if r.psnr is None or ref_row.psnr is None else f"{r.psnr - ref_row.psnr:+.2f}")
            lines.append("| " + " | ".join(cells) + " |")
    lines += ["", SIZE_NOTE]
    if points:
        lines.append("RP: the curve's rate points rp01 (lowest rate) to rp04, as MPEG's Gaussian-splat-coding test "
                     "conditions name them, on its Pareto front (a point another beats names none); a curve of more "
                     "than four "
                     "points names four spread over its log rate.")
    if show_yuv:
        lines.append("YUV-PSNR: BT.709 YUV 4:2:0, (6 Y + U + V) / 8, as MPEG video coding reports quality.")
    if ref_row:
        lines.append(f"Reference for the last two columns: {ref_row.family} / {ref_row.name}."
                     + (f" {elsewhere} row(s) scored on another test set than it are not compared with it (–)."
                        if elsewhere else ""))
    if bd:
        lines += ["", f"### Bjøntegaard deltas against {baseline} ({bd_method} interpolation)", "",
                  "| Curve | Points | BD-rate (%) | BD-PSNR (dB) | Note |", "|---|---:|---:|---:|---|"]
        for b in bd:
            lines.append(f"| {b.family} | {b.points} | {_f(b.bd_rate, '+.2f')} | {_f(b.bd_psnr, '+.3f')} | "
                         f"{b.note} |")
        lines += ["", "Negative BD-rate: the curve needs less rate than the baseline for the same PSNR; "
                      "positive BD-PSNR: higher quality at the same rate. Averaged over the overlapping range only."]
    return "\n".join(lines) + "\n"


LOG_RATE_SPAN = 10.0


def rate_axis_is_log(rows: Sequence[ReportRow], metric: str = "psnr") -> bool:
    """Whether the RD plot of `rows` uses a log rate axis: its plotted rates span more than LOG_RATE_SPAN."""
    rates = [float(r.mbps) for family in _families(rows).values() for r in _curve(family)
             if r.mbps is not None and getattr(r, metric) is not None]
    return bool(rates) and max(rates) > LOG_RATE_SPAN * min(rates)


# Beyond this many plotted points, point labels would overlap one another; the legend and the report's table name
# them instead. Beyond LEGEND_INSIDE_MAX families the legend would cover the curves, so it goes beside the axes.
LABELLED_POINTS_MAX = 16
LEGEND_INSIDE_MAX = 4


def rd_figure(rows: Sequence[ReportRow], title: str, baseline: str | None, metric: str = "psnr") -> Any:
    """The RD plot as a matplotlib Figure (the caller saves and closes it): Mbps vs PSNR, one line per family
    (points in rate order). The rate axis is logarithmic when the plotted rates span more than LOG_RATE_SPAN (codec
    points at a tenth of the uncompressed rate would otherwise crowd its left edge); each point is labelled by its
    setting while the plot has at most LABELLED_POINTS_MAX points."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    markers = ["o", "s", "^", "D", "v", "P", "X", "*"]
    curves: list[tuple[str, list[ReportRow]]] = []
    for family, members in _families(rows).items():
        curve = [r for r in _curve(members) if getattr(r, metric) is not None]
        if curve:
            curves.append((family, curve))
    legend_beside = len(curves) > LEGEND_INSIDE_MAX
    label_points = sum(len(c) for _, c in curves) <= LABELLED_POINTS_MAX
    # tab10 repeats its colours after ten families; tab20 (its hues light and dark) keeps twenty apart.
    palette = 10 if len(curves) <= 10 else 20
    colours = [plt.get_cmap(f"tab{palette}")(k) for k in range(palette)]
    fig, ax = plt.subplots(figsize=(9.6 if legend_beside else 6.4, 4.6), dpi=100)
    if rate_axis_is_log(rows, metric):
        ax.set_xscale("log")
    for i, (family, curve) in enumerate(curves):
        xs = np.array([r.mbps for r in curve], dtype=float)
        ys = np.array([getattr(r, metric) for r in curve], dtype=float)
        label = f"{family} (baseline)" if family == baseline else family
        # The line joins the Pareto front, which the BD deltas use; dominated points are markers alone.
        line = _front(curve) if metric == "psnr" else curve
        colour, marker = colours[i % len(colours)], markers[i % len(markers)]
        ax.plot(np.array([r.mbps for r in line], dtype=float),
                np.array([getattr(r, metric) for r in line], dtype=float),
                marker=marker, color=colour,
                linewidth=1.8 if family == baseline else 1.4,
                linestyle="--" if family == baseline else "-", markersize=6, label=label)
        if len(line) < len(curve):
            ax.plot(xs, ys, marker=marker, color=colour, linestyle="none", markersize=6, fillstyle="none")
        if label_points:
            for r, x, y in zip(curve, xs, ys):
                ax.annotate(r.name, (x, y), textcoords="offset points", xytext=(4, -11), fontsize=7, alpha=0.75)
    ax.set_xlabel("Bitrate (Mbps)")
    ax.set_ylabel("PSNR (dB)" if metric == "psnr" else metric.upper())
    # long plan titles would run past the figure
    ax.set_title(textwrap.fill(title, 60, break_on_hyphens=False), fontsize=11)
    ax.margins(x=0.1, y=0.08)
    ax.grid(True, alpha=0.3)
    if legend_beside:
        ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8, frameon=True)
    else:
        ax.legend(loc="lower right", fontsize=8, frameon=True)
    fig.tight_layout()
    return fig


def rd_plot(rows: Sequence[ReportRow], png: Path, svg: Path | None, title: str, baseline: str | None,
            metric: str = "psnr") -> None:
    """rd_figure written to `png` (and `svg`), each atomically."""
    import matplotlib.pyplot as plt

    fig = rd_figure(rows, title, baseline, metric)
    try:
        with atomic_path(png) as tmp:
            fig.savefig(tmp, format="png", dpi=200, bbox_inches="tight")
        if svg is not None:
            with atomic_path(svg) as tmp:
                fig.savefig(tmp, format="svg", bbox_inches="tight")
    finally:
        plt.close(fig)


def make_report(
    rows: Iterable[ReportRow | Mapping[str, Any]],
    out_dir: str | Path,
    baseline: str | None = None,
    *,
    title: str = "Rate-distortion results",
    bd_method: Method = "pchip",
    stem: str = "report",
    notes: Sequence[str] = (),
    baseline_may_be_missing: bool = False,
) -> Report:
    """Write OUT/<stem>.md (table + BD deltas), OUT/<stem>_rd.png/.svg (RD plot) and OUT/<stem>.json.

    A `baseline` that names no row is an error, unless `baseline_may_be_missing` (an experiment whose baseline runs
    failed): then the report has no BD deltas and says why."""
    parsed = [r if isinstance(r, ReportRow) else ReportRow.from_mapping(r) for r in rows]
    return _write_report(parsed, Path(out_dir), baseline, title, bd_method, stem, notes, baseline_may_be_missing)


def remove_report(out_dir: str | Path, stem: str = "report") -> None:
    """Remove the files make_report writes, where no report can be made now: an earlier one must not stand for it."""
    for suffix in (".md", "_rd.png", "_rd.svg", ".json"):
        (Path(out_dir) / f"{stem}{suffix}").unlink(missing_ok=True)


def _write_report(rows: list[ReportRow], out_dir: Path, baseline: str | None, title: str, bd_method: Method,
                  stem: str, notes: Sequence[str], baseline_may_be_missing: bool = False) -> Report:
    out_dir.mkdir(parents=True, exist_ok=True)
    # The experiment runner's rows come from the records alone: one of another run's model (a file copied into the
    # run's folder, `stgc.eval.evaluate.foreign_model`) is no point of this run, however it was given.
    foreign = [r for r in rows if r.extra.get("foreign")]
    if foreign:
        rows = [r for r in rows if not r.extra.get("foreign")]
        notes = [*notes, "Left out, holding another run's model than the run they were given as: "
                 + "; ".join(f"{r.name} ({r.extra['foreign']})" for r in foreign)]
    try:
        base = resolve_baseline(rows, baseline)
    except ValueError as exc:
        if not baseline_may_be_missing:
            raise
        base, notes = None, [*notes, f"No BD deltas: {exc}; its runs have no results."]
    rows, test_sets = split_test_sets(rows, base)
    if test_sets:
        log.warning("the report's rows were scored on %d different test sets: each is a curve of its own, compared "
                    "with no other test set's (see %s)", len(test_sets), out_dir / f"{stem}.md")
    bd = bd_table(rows, base, bd_method)
    png = svg = None
    if any(r.mbps is not None and r.psnr is not None for r in rows):
        png, svg = out_dir / f"{stem}_rd.png", out_dir / f"{stem}_rd.svg"
        rd_plot(rows, png, svg, title, base)
    else:  # nothing to plot: an earlier report's plot must not stand beside this table
        for stale in (out_dir / f"{stem}_rd.png", out_dir / f"{stem}_rd.svg"):
            stale.unlink(missing_ok=True)
    md = out_dir / f"{stem}.md"
    with atomic_open(md, "w") as f:
        f.write(f"# {title}\n\n")
        if png is not None:
            f.write(f"![Rate-distortion: PSNR of the test views against Mbps]({png.name})\n\n")
        if test_sets:
            f.write(f"**Warning: these results were scored on {len(test_sets)} different test sets.** Rates and "
                    "PSNRs of different test views are not comparable: each test set's rows make curves of their "
                    "own (\"[test set X]\"), and BD deltas and the change against the reference are given only "
                    f"between rows of one test set (the baseline's is A).\n\n")
            f.writelines(f"- Test set {label}: {describe_test_set(t)}\n" for label, t in test_sets.items())
            f.write("\n")
        f.write(markdown_table(rows, base, bd, "Results", bd_method))
        for note in notes:
            f.write(f"\n{note}\n")
    json_path = out_dir / f"{stem}.json"
    points = rate_points(rows)
    write_json(json_path, {"title": title, "baseline": base, "bd_method": bd_method, "size_note": SIZE_NOTE,
                           **({"test_sets": test_sets} if test_sets else {}),
                           "rows": [asdict(r) | ({"rate_point": points[id(r)]} if id(r) in points else {})
                                    for r in rows], "bd": [asdict(b) for b in bd]})
    return Report(out_dir, md, png, svg, json_path, rows, bd, base)


# ------------------------------------------------------------------------------------------- runs


def describe_run(run_dir: Path, config: Mapping[str, Any] | None) -> tuple[str, str]:
    """(family, setting) of a run from its config when no experiment.json names them."""
    cfg = config or {}
    comp = cfg.get("compaction") or {}
    data = cfg.get("data") or {}
    preprocess = data.get("preprocess") or "none"
    window = (cfg.get("train") or {}).get("quantization_aware")
    window = window if isinstance(window, dict) else {}
    if window.get("iterations"):  # a rate-aware window (fine-tuning or not) makes another method than STG's
        if window.get("simulate") is False:  # the control: the window's learning rates without the quantization
            family = "rate-aware control"
        else:
            family = "learned mask" if window.get("mask") else "rate-aware"
        setting = run_dir.name
    elif comp.get("method", "none") not in (None, "none", "reference"):  # a reference run prunes nothing
        family = f"ST-KNN ({comp.get('criterion', 'timestamp')})"
        setting = f"Case {comp['case']}" if comp.get("case") else run_dir.name
    else:
        family = "STG"
        setting = "no preprocessing" if preprocess == "none" else f"preprocessing {preprocess}"
    return family, setting


def rows_from_run(run_dir: str | Path, include_codec: bool = True, plan: str | None = None) -> list[ReportRow]:
    """Report rows of one run: its eval.json, and every eval_<bitstream>.json beside it, named as the experiment
    plan `plan` labelled the run (RUN/experiment.json keeps each plan's family and label of a run that several plans
    share; without `plan`, or for a run that plan did not list, the first plan's)."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise DataError(run_dir, "not a run directory")
    run = Run(run_dir)
    config = run.read_config()
    for name in ("data", "model", "train", "compaction"):
        # Restored runs' config.json holds only what a bitstream embeds: any section may be absent or null.
        if config is not None and config.get(name) is not None and not isinstance(config[name], dict):
            raise FormatError(run.config_path, f"its {name!r} section is {type(config[name]).__name__} "
                                               f"{config[name]!r:.40}, not an object")
    meta = read_json_object(run.experiment_path) or {}
    plans = meta.get("plans")
    if plan is not None and isinstance(plans, dict) and isinstance(plans.get(plan), dict):
        meta = {**meta, **plans[plan]}
    family, setting = describe_run(run_dir, config)
    family = str(meta.get("family") or family)
    setting = str(meta.get("label") or meta.get("name") or setting)
    rows = []
    summary = run.read_summary(strict=False)
    saved_data = (config or {}).get("data")
    saved_data = saved_data if isinstance(saved_data, dict) else {}

    def test_set(record: Mapping[str, Any]) -> dict[str, Any]:
        # Records the trainer wrote before they named their data and downscale: the run's config says them.
        return {"data": record.get("data") or saved_data.get("path"),
                "downscale": record.get("downscale", saved_data.get("downscale"))}

    record = run.read_eval()
    if record is not None and scored_earlier_model(record, summary):
        log.warning("%s: left out of the report: it scored the model before the training finished (stgc eval the "
                    "run again)", run.eval_paths()[0])
    elif record is not None:
        # A run still training, scored by `stgc eval`: its numbers are not the run's result, and the table says so.
        rows.append(_row_of(run.eval_paths()[0], {**record_fields(record), **test_set(record),
                                                  "name": _named(setting, record), "family": family,
                                                  "run": run_dir.name, "run_dir": str(run_dir)}))
    if include_codec:
        for path in sorted(run_dir.glob("eval_*.json")):
            rec = read_json_object(path)
            if rec is None or _on_other_data(rec, config):
                continue
            point = path.stem.removeprefix("eval_")
            bitstream = str(rec.get("bitstream") or f"{point}.stgc")
            own_record = run.eval_paths(bitstream=run_dir / Path(bitstream).name)[0].name
            if path.name != own_record:
                # A copy of a record under another name (saved `stgc eval --json` output) is no point of its own.
                log.warning("%s: left out of the report: it is not the record stgc eval writes for %s (that is "
                            "%s)", path, bitstream, own_record)
                continue
            if not Run.scored_this_bitstream(rec, run_dir / bitstream):
                log.warning("%s: left out of the report: %s is missing or was written again after this "
                            "evaluation (stgc eval it again)", path, bitstream)
                continue
            if rec.get("foreign"):
                log.warning("%s: left out of the report: %s holds another run's model (%s)", path, bitstream,
                            rec["foreign"])
                continue
            if scored_earlier_model(rec, summary):
                log.warning("%s: left out of the report: %s holds the model of iteration %s, not the one the run "
                            "ended with (compress and evaluate the run again)", path, bitstream, rec.get("iterations"))
                continue
            # The experiment runner's model_q<Q>.stgc is its "q<Q>" point, as the runner's own rows name it.
            label = point.removeprefix("model_") if re.fullmatch(r"model_q\d+", point) else point
            rows.append(_row_of(path, {**record_fields(rec), **test_set(rec),
                                       "name": _named(f"{setting} {label}", rec),
                                       "family": f"{family}{CODEC_SUFFIX}", "run": run_dir.name,
                                       "run_dir": str(run_dir), "bitstream": bitstream}))
    return rows


def _row_of(path: Path, fields: Mapping[str, Any]) -> ReportRow:
    try:
        return ReportRow.from_mapping(fields)
    except (TypeError, ValueError) as exc:
        raise FormatError(path, f"not an evaluation record stgc can report: {exc}") from None


def _named(name: str, record: Mapping[str, Any]) -> str:
    return f"{name} (half-trained)" if record.get("training_finished") is False else name


def scored_earlier_model(record: Mapping[str, Any], summary: Mapping[str, Any] | None) -> bool:
    """Whether a record of the run (its eval.json, or a bitstream's) scored a model the finished run does not end
    with: made while the run trained (`stgc eval` of the half-trained run), or of an earlier iteration's file.
    Records that name neither (written before the fields existed, or by other tools) are taken as they are."""
    if not (summary and summary.get("finished")):
        return False
    if record.get("training_finished") is False:
        return True
    return "iterations" in record and record["iterations"] != summary.get("iterations")


def _on_other_data(record: Mapping[str, Any], config: Mapping[str, Any] | None) -> bool:
    """An evaluation on data other than the run's own (`stgc eval RUN --data OTHER`: eval_on_<name>.json,
    eval_<stem>_on_<name>.json): not a rate point of the run. Records written before `other_data` existed are
    told by the data folder they name."""
    if record.get("other_data"):
        return True
    saved = ((config or {}).get("data") or {}).get("path")
    scored = record.get("data")
    return bool(saved and scored) and not same_place(str(scored), str(saved))


RECORD_FIELDS = ("num_gaussians", "size_mb", "mbps", "psnr", "psnr_yuv", "ssim", "lpips", "fps", "train_seconds")


def record_fields(record: Mapping[str, Any]) -> dict[str, Any]:
    """The eval.json values a report row (and the experiment's results.csv) carries: its numbers, the test set it
    was scored on (TEST_SET_FIELDS) and, for a file of another run's model, why it is one (`foreign`): make_report
    compares rows of one test set only and leaves such files out, for rows read from runs and for the experiment
    runner's alike."""
    return {k: record.get(k) for k in (*RECORD_FIELDS, *TEST_SET_FIELDS, "foreign")}


def report_from_runs(
    run_dirs: Sequence[str | Path],
    out_dir: str | Path,
    baseline: str | None = None,
    *,
    title: str = "Rate-distortion results",
    include_codec: bool = True,
    bd_method: Method = "pchip",
    plan: str | None = None,
) -> Report:
    """`make_report` over any set of runs, each named as the experiment plan `plan` labelled it (`rows_from_run`).
    Runs without eval.json are listed in the report as missing."""
    if plan is not None:
        known = {name for d in run_dirs for name in
                 ((read_json_object(Run(d).experiment_path, strict=False) or {}).get("plans") or {})}
        if plan not in known:  # a misspelt name would name every run as the first plan did, silently
            raise DataError(None, f"--plan {plan!r}: no run's experiment.json lists that plan"
                                  + (f" (they list: {', '.join(sorted(map(str, known)))})" if known else ""))
    rows: list[ReportRow] = []
    missing = []
    for d in run_dirs:
        found = rows_from_run(d, include_codec, plan)
        if not found:
            missing.append(str(d))
        rows.extend(found)
    if not rows:
        raise DataError(None, f"none of the runs has an eval.json: {', '.join(map(str, run_dirs))}")
    notes = ["Runs without evaluation (not in the table): " + ", ".join(missing)] if missing else []
    return make_report(rows, out_dir, baseline, title=title, bd_method=bd_method, notes=notes)
