"""Spatiotemporal KNN compaction of Spacetime Gaussians with a rendering-loss-adaptive pruning ratio.

Lee et al., "Efficient 4DGS Model Compression Using a Spatiotemporal KNN Algorithm" (JBE 2024), section III; the
exact rules and defaults are in docs/compaction.md.
"""

from .compactor import ProbeResult, STKNNCompactor
from .config import CASE_WINDOWS, PAPER_RULE, CompactionConfig, PruningSchedule, resolve_schedule
from .controller import AdaptiveRatio, LossSmoother, budget_for_psnr_drop
from .matching import (
    PairMatches,
    match_pairs,
    match_pairs_bruteforce,
    match_spatiotemporal_pairs,
    nearest_other,
    nearest_other_bruteforce,
    spacetime_features,
)
from .plot import plot_compaction, read_compaction_log
from .pruning import PruneSelection, removal_scores, select_removals

__all__ = [
    "CASE_WINDOWS",
    "PAPER_RULE",
    "AdaptiveRatio",
    "CompactionConfig",
    "LossSmoother",
    "PairMatches",
    "PruneSelection",
    "PruningSchedule",
    "STKNNCompactor",
    "budget_for_psnr_drop",
    "ProbeResult",
    "match_pairs",
    "match_pairs_bruteforce",
    "match_spatiotemporal_pairs",
    "nearest_other",
    "nearest_other_bruteforce",
    "plot_compaction",
    "read_compaction_log",
    "removal_scores",
    "resolve_schedule",
    "select_removals",
    "spacetime_features",
]
