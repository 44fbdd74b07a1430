"""STG training: configs and presets, the loop, density control, checkpoints and resume."""

from stgc.train.checkpoint import load_checkpoint, save_checkpoint
from stgc.train.config import (
    CPU_SCHEDULE_SCALE,
    PRESETS,
    DensifyConfig,
    EMSConfig,
    FloaterConfig,
    LearningRates,
    Schedule,
    TrainConfig,
    resolve_schedule,
    train_preset,
)
from stgc.train.loop import (
    TestEvaluator,
    TestScore,
    Trainer,
    build_initial_model,
    train,
)

__all__ = [
    "CPU_SCHEDULE_SCALE",
    "PRESETS",
    "DensifyConfig",
    "EMSConfig",
    "FloaterConfig",
    "LearningRates",
    "Schedule",
    "TestEvaluator",
    "TestScore",
    "TrainConfig",
    "Trainer",
    "build_initial_model",
    "load_checkpoint",
    "resolve_schedule",
    "save_checkpoint",
    "train",
    "train_preset",
]
