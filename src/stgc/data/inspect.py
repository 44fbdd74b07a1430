"""`stgc data inspect PATH`: what a dataset holds, as a dict and as a rich table."""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.table import Table

from .readers import open_dataset


def inspect(path: str | Path, format: str = "auto", decode: bool = False, **kwargs: Any) -> dict[str, Any]:
    """Summary of the dataset at `path` (all frames unless start/duration are given) plus point availability.
    decode: also decode every image and mask file (a truncated or corrupt one is a DataError naming it)."""
    dataset = open_dataset(path, format=format, **kwargs)
    info = dataset.summary()
    info["decoded_files"] = dataset.verify_images(progress=True) if decode else None
    info["masks"] = dataset.has_masks
    info["near_plane"] = dataset.near_plane
    info["official_config"] = dataset.official_config
    if dataset.has_points:
        counts = []
        for frame in dataset.frames:
            got = dataset.data_points(frame)
            counts.append(0 if got is None else len(got[0]))
        info["points_per_frame"] = {"min": min(counts), "max": max(counts), "total": sum(counts)}
    else:
        info["points_per_frame"] = None
    return info


def _bytes(n: int) -> str:
    size = float(n)
    for unit in ("B", "KiB", "MiB", "GiB"):
        if size < 1024 or unit == "GiB":
            return f"{size:.0f} {unit}" if unit == "B" else f"{size:.1f} {unit}"
        size /= 1024
    return str(size)


def _time_rule(info: dict[str, Any]) -> str:
    """How each frame's time is set: STG's rule, or (frames that are ranks of unevenly spaced times) the data's."""
    if not info["times_from_positions"]:
        return f"t = (frame - {info['start']}) / {info['duration']}"
    first, last = info["times"]
    return (f"t from the transforms' time values (frames are ranks of unevenly spaced times), "
            f"t = {first:.4g}..{last:.4g}")


def inspect_text(path: str | Path, **kwargs: Any) -> str:
    """The `inspect` summary rendered as a plain-text table (no terminal colours)."""
    info = inspect(path, **kwargs)
    table = Table(title=f"{info['name']} ({info['format']})", show_header=False)
    table.add_column("field", style="bold")
    table.add_column("value")
    res = ", ".join(f"{w}x{h}" for w, h in info["resolution"])
    native = ", ".join(f"{w}x{h}" for w, h in info["native_resolution"])
    pts = info["points_per_frame"]
    rows = [
        ("path", info["root"]),
        ("format", info["format"]),
        ("frames", f"{info['num_frames']} ({info['frames'][0]}..{info['frames'][-1]}), fps {info['fps']:g}, "
                   + _time_rule(info)),
        ("cameras", f"{info['views']} views: {len(info['train_views'])} train, {len(info['test_views'])} test"),
        ("test views", ", ".join(info["test_views"]) or "-"),
        ("train views", ", ".join(info["train_views"])),
        ("images", f"{info['train_images']} train + {info['test_images']} test"),
        ("resolution", res + (f" (native {native}, downscale {info['downscale']:g})" if res != native else "")),
        ("scene extent", f"{info['scene_extent']:.4g} (1.1 x max camera distance from their mean)"),
        ("memory", f"{_bytes(info['memory_uint8_bytes'])} as uint8, {_bytes(info['memory_float32_bytes'])} as float32"),
        ("initial points", "none shipped (triangulate or random)" if pts is None else
         f"{info['points']}: {pts['total']} in all, {pts['min']}..{pts['max']} per frame"),
        ("masks", "foreground masks for the training views" if info["masks"] else "none"),
        ("near plane", f"{info['near_plane']:g}"),
        ("official config", "none: the official STG defaults" if info["official_config"] is None else
         f"{info['official_config']} (options left unset train as its official configs: stgc.official)"),
        ("decoded", "not checked (add --decode to decode every file)" if info["decoded_files"] is None
         else f"all {info['decoded_files']} image and mask files decode"),
    ]
    rows += [("note", n) for n in info["notes"]]
    for key, value in rows:
        table.add_row(key, str(value))
    buffer = io.StringIO()
    Console(file=buffer, width=110, no_color=True, color_system=None).print(table)
    return buffer.getvalue()
