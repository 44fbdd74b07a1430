"""Options of `stgc experiment` (the plan runner)."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class ExperimentConfig:
    plan: str = field(default="table2", metadata={
        "help": "table2 (STG w/o and with preprocessing, proposed Cases 1-4), table3 (Cases 1-4, criterion scale "
                "vs timestamp) or a PLAN.toml listing runs as {name, family, label, overrides}"})
    preset: str = field(default="cpu", metadata={"help": "training preset passed to every run (cpu or paper)"})
    preprocess: str = field(default="stg-isolated", metadata={
        "help": "data.preprocess of the 'with preprocessing' runs of the built-in plans (stg-isolated = official "
                "STG code, closest-pairs = the paper's description)"})
    codec_qualities: list[int] = field(default_factory=list, metadata={
        "help": "also compress every run to .stgc at these quality levels and evaluate each as a rate point"})
    bd_method: str = field(default="pchip", metadata={
        "help": "Bjøntegaard interpolation of the report: pchip (JCT-VC/JVET spreadsheets) or cubic (VCEG-M33)"})
