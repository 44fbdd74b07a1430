"""Multi-view video datasets: cameras, readers for common layouts, initial point clouds.

Public API:
    open_dataset(path, format="auto", downscale=1, start=None, duration=None, test_cameras=None, fps=None)
        -> Dataset (.train/.test cameras, .train_at/.test_at(frame), .load_image, .scene_extent, .summary)
    initial_points(dataset, source="auto"|"data"|"triangulate"|"random", frames=None,
                   max_points_per_frame=None, seed=0) -> PointCloud(xyz, rgb, time)
    preprocess_points(cloud, mode="none"|"stg-isolated"|"closest-pairs", fraction=0.25) -> (cloud, report)
    inspect(path) -> dict, inspect_text(path) -> str
    DataConfig: the data options with help texts.
"""

from .cameras import (
    Camera,
    colmap_to_w2c,
    llff_to_w2c,
    omaf_to_w2c,
    opencv_to_corner_K,
    opengl_c2w_to_w2c,
    qvec_to_rotmat,
    rotmat_to_qvec,
)
from .config import DataConfig, initial_points_from_config
from .dataset import Dataset, SourceScene, segments
from .inspect import inspect, inspect_text
from .points import PointCloud, initial_points
from .preprocess import PreprocessReport, preprocess_points
from .readers import detect_format, format_names, open_dataset

__all__ = [
    "Camera",
    "DataConfig",
    "Dataset",
    "PointCloud",
    "PreprocessReport",
    "SourceScene",
    "colmap_to_w2c",
    "detect_format",
    "format_names",
    "initial_points",
    "initial_points_from_config",
    "inspect",
    "inspect_text",
    "llff_to_w2c",
    "omaf_to_w2c",
    "open_dataset",
    "opencv_to_corner_K",
    "opengl_c2w_to_w2c",
    "preprocess_points",
    "qvec_to_rotmat",
    "rotmat_to_qvec",
    "segments",
]
