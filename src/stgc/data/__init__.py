"""Multi-view video datasets: cameras, readers for common layouts, initial point clouds."""

from .cameras import Camera
from .dataset import Dataset, SourceScene, segments
from .readers import FORMATS, detect_format, open_dataset

__all__ = ["Camera", "Dataset", "SourceScene", "segments", "FORMATS", "detect_format", "open_dataset"]
