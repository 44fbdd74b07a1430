"""A plan trained over several seeds: each entry's mean over its seeds, the spread, and its change against the
baseline seed by seed.

Two trainings of one configuration with different seeds end a few tenths of a dB apart on a real capture, so a
single pair of runs cannot tell a change of that size from the seed. Seed by seed the pruned run and its baseline
share everything up to the first prune; the paired differences (`delta_psnr`, `removed`) are what a claim such as
"half the Gaussians removed within 0.3 dB" is about, and their mean and spread are what the report gives.
"""

from __future__ import annotations

import csv
import math
import statistics
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from stgc.eval.report import CODEC_SUFFIX, TEST_SET_FIELDS, ReportRow, same_test_set
from stgc.experiment.plans import Plan
from stgc.fileio import atomic_open

SPREAD_COLUMNS = ("entry", "family", "label", "seeds", "num_gaussians_mean", "psnr_mean", "psnr_sd", "psnr_min",
                  "psnr_max", "mbps_mean", "size_mb_mean", "ssim_mean", "delta_psnr_mean", "delta_psnr_sd",
                  "delta_psnr_min", "delta_psnr_max", "removed_mean", "removed_min", "removed_max", "paired_seeds")


@dataclass
class EntrySpread:
    """One plan entry (or one of its codec points) over the seeds that have a result."""

    entry: str  # the plan entry's name, "-q<Q>" added for a codec point
    family: str
    label: str
    position: tuple[int, int, str] = (0, 0, "")  # the entry's place in the plan, then its bitstream's name
    rows: dict[int, ReportRow] = field(default_factory=dict)  # by seed
    delta_psnr: dict[int, float] = field(default_factory=dict)  # against the baseline run of the same seed, dB
    removed: dict[int, float] = field(default_factory=dict)  # share of the baseline's Gaussians gone, same seed

    def values(self, name: str) -> list[float]:
        found = (getattr(row, name) for _, row in sorted(self.rows.items()))
        return [float(v) for v in found if v is not None]

    def mean_row(self) -> ReportRow:
        """The entry's point in the report: each number the mean over its seeds."""
        def mean(name: str) -> float | None:
            return _mean(self.values(name))
        gaussians = mean("num_gaussians")
        rows = list(self.rows.values())
        # The report's other columns (YUV-PSNR, FPS) read the record's numbers: the point's are the seeds' means.
        numbers = {key: statistics.fmean(float(row.extra[key]) for row in rows) for key in rows[0].extra
                   if all(_is_number(row.extra.get(key)) for row in rows)} if rows else {}
        return ReportRow(name=self.label, family=self.family, mbps=mean("mbps"), psnr=mean("psnr"),
                         num_gaussians=None if gaussians is None else round(gaussians), size_mb=mean("size_mb"),
                         ssim=mean("ssim"), lpips=mean("lpips"),
                         extra={**numbers, "run": self.entry, "seeds": sorted(self.rows),
                                **_shared_test_set(rows)})

    def paired(self) -> tuple[list[float], list[float]]:
        """The changes against the baseline, seed by seed: PSNR (dB) and share of Gaussians removed."""
        return ([v for _, v in sorted(self.delta_psnr.items())], [v for _, v in sorted(self.removed.items())])

    def csv_row(self) -> dict[str, object]:
        psnr = self.values("psnr")
        delta, removed = self.paired()
        return {"entry": self.entry, "family": self.family, "label": self.label,
                "seeds": " ".join(map(str, sorted(self.rows))),
                "num_gaussians_mean": _mean(self.values("num_gaussians")), "psnr_mean": _mean(psnr),
                "psnr_sd": _sd(psnr), "psnr_min": min(psnr, default=None), "psnr_max": max(psnr, default=None),
                "mbps_mean": _mean(self.values("mbps")), "size_mb_mean": _mean(self.values("size_mb")),
                "ssim_mean": _mean(self.values("ssim")), "delta_psnr_mean": _mean(delta), "delta_psnr_sd": _sd(delta),
                "delta_psnr_min": min(delta, default=None), "delta_psnr_max": max(delta, default=None),
                "removed_mean": _mean(removed), "removed_min": min(removed, default=None),
                "removed_max": max(removed, default=None), "paired_seeds": " ".join(map(str, sorted(self.delta_psnr)))}


def _is_number(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _mean(values: Sequence[float]) -> float | None:
    return statistics.fmean(values) if values else None


def _sd(values: Sequence[float]) -> float | None:
    """The sample standard deviation (n - 1), None below two values."""
    return statistics.stdev(values) if len(values) > 1 else None


def _shared_test_set(rows: Iterable[ReportRow]) -> dict[str, object]:
    """The first seed's test-set fields where every seed's row was scored on that test set (the report keeps rows
    of different test sets apart); none where they differ."""
    rows = list(rows)
    if not rows or not all(same_test_set(rows[0], row) for row in rows[1:]):
        return {}
    return {key: rows[0].extra[key] for key in TEST_SET_FIELDS if rows[0].extra.get(key) is not None}


def baseline_entry(plan: Plan) -> str | None:
    """The plan entry each entry is paired against seed by seed: the baseline where it names a run, else the first
    run of the baseline family (a codec family's runs' float models), else the plan's first run."""
    entries = [spec for spec in plan.runs if spec.seed == plan.seeds[0]] if plan.seeds else list(plan.runs)
    if not entries:
        return None
    wanted = plan.baseline
    if wanted is not None and wanted.endswith(CODEC_SUFFIX):
        wanted = wanted[: -len(CODEC_SUFFIX)]
    for spec in entries:
        if wanted is not None and spec.entry_name == wanted:
            return spec.entry_name
    for spec in entries:
        if wanted is None or spec.family == wanted:
            return spec.entry_name
    return None


def seed_spread(plan: Plan, rows: Mapping[tuple[str, str | None], ReportRow]) -> list[EntrySpread]:
    """Each entry's spread over the seeds of `plan`, from the report rows of its runs, keyed (run folder name,
    bitstream or None for the run's own model). Entries in plan order, each followed by its codec points."""
    specs = {spec.name: spec for spec in plan.runs}
    order = {spec.entry_name: index for index, spec in reversed(list(enumerate(plan.runs)))}
    spreads: dict[str, EntrySpread] = {}
    for (run, bitstream), row in rows.items():
        spec = specs.get(run)
        if spec is None or spec.seed is None:
            continue
        entry = spec.entry_name + ("" if bitstream is None else f"-{Path(bitstream).stem.removeprefix('model_')}")
        if entry not in spreads:
            # (by the bitstream's name's length first: model_q4 before model_q10)
            spreads[entry] = EntrySpread(entry, row.family, row.name,
                                         (order[spec.entry_name], len(bitstream or ""), bitstream or ""))
        spreads[entry].rows[spec.seed] = row
    base = baseline_entry(plan)
    baseline = spreads.get(base) if base is not None else None
    if baseline is not None:
        for spread in spreads.values():
            for seed, row in spread.rows.items():
                reference = baseline.rows.get(seed)
                if reference is None or not same_test_set(row, reference):  # other views: no change
                    continue
                if row.psnr is not None and reference.psnr is not None and math.isfinite(row.psnr - reference.psnr):
                    spread.delta_psnr[seed] = row.psnr - reference.psnr
                if row.num_gaussians is not None and reference.num_gaussians:
                    spread.removed[seed] = 1.0 - row.num_gaussians / reference.num_gaussians
    return sorted(spreads.values(), key=lambda spread: spread.position)


def spread_markdown(spreads: Sequence[EntrySpread], baseline: str | None) -> str:
    """The table the report adds: each entry's mean and spread over its seeds, and the change against `baseline`
    seed by seed (mean, sample standard deviation, range)."""
    def number(values: Sequence[float], digits: int = 2, sign: str = "") -> str:
        mean = _mean(values)
        return "–" if mean is None else f"{mean:{sign},.{digits}f}"

    def sd(values: Sequence[float]) -> str:
        spread = _sd(values)
        return "–" if spread is None else f"{spread:.2f}"

    lines = ["## Over the seeds", "",
             f"Each run trained once per seed; a row's numbers are means over its seeds. The change against "
             f"`{baseline}` (its float model, also where the BD deltas' baseline is a codec curve) is taken seed by "
             "seed (the runs of one seed share everything up to where they differ), then averaged: mean ± sample "
             "standard deviation [min, max]. A codec point's Gaussians are those its file stores (with the default "
             "codec.drop_invisible, none that no frame shows).", "",
             "| run | seeds | Gaussians | PSNR dB | PSNR sd | vs baseline dB | removed vs baseline | Mbps |",
             "|---|---|---:|---:|---:|---|---|---:|"]
    for spread in spreads:
        delta, removed = spread.paired()
        psnr = spread.values("psnr")
        change = "–" if not delta else f"{number(delta, sign='+')} ± {sd(delta)} [{min(delta):+.2f}, {max(delta):+.2f}]"
        gone = "–" if not removed else (f"{100 * statistics.fmean(removed):.1f} % "
                                         f"[{100 * min(removed):.1f}, {100 * max(removed):.1f}]")
        seeds = " ".join(map(str, sorted(spread.rows)))
        lines.append(f"| {spread.label} ({spread.entry}) | {seeds} | {number(spread.values('num_gaussians'), 0)} | "
                     f"{number(psnr)} | {sd(psnr)} | {change} | {gone} | {number(spread.values('mbps'), 3)} |")
    return "\n".join(lines) + "\n"


def write_spread_csv(path: Path, spreads: Sequence[EntrySpread]) -> None:
    with atomic_open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=SPREAD_COLUMNS)
        writer.writeheader()
        for spread in spreads:
            writer.writerow({k: ("" if v is None else v) for k, v in spread.csv_row().items()})
