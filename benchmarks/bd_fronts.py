"""BD deltas of every committed report, recomputed from its results CSV with today's `bd_table` (each curve reduced to
its Pareto front), beside the values its report.json was written with. Prints the rows that moved.

    .venv/bin/python benchmarks/bd_fronts.py
"""

from __future__ import annotations

import csv
import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))

from stgc.eval.report import ReportRow, bd_table  # noqa: E402


def _fmt(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.2f}"


def main() -> int:
    import argparse

    argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None).parse_args()
    print("| report | curve | baseline | BD-rate written | now | BD-PSNR written | now | note |")
    print("|---|---|---|---:|---:|---:|---:|---|")
    for path in sorted((REPO / "benchmarks" / "results").glob("*/*/results-*.csv")):
        # results-<plan>.csv and report-<plan>/: several plans may share one folder.
        report = path.parent / f"report-{path.stem.removeprefix('results-')}" / "report.json"
        if not report.is_file():
            continue
        with path.open(newline="") as f:
            rows = [ReportRow(name=r["label"], family=r["family"], mbps=float(r["mbps"]), psnr=float(r["psnr"]))
                    for r in csv.DictReader(f) if r.get("status") != "failed" and r.get("mbps") and r.get("psnr")]
        written = json.loads(report.read_text())
        baseline = written.get("baseline")
        now = {b.family: b for b in bd_table(rows, baseline, written.get("bd_method", "pchip"))}
        for old in written.get("bd", []):
            new = now.get(old["family"])
            if new is None:
                continue
            before = (_fmt(old.get("bd_rate")), _fmt(old.get("bd_psnr")))
            after = (_fmt(new.bd_rate), _fmt(new.bd_psnr))
            if before != after:
                print(f"| {path.parent.relative_to(REPO / 'benchmarks' / 'results')} | {old['family']} | {baseline} "
                      f"| {before[0]} | {after[0]} | {before[1]} | {after[1]} | {new.note} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
