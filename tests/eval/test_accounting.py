"""Size / bitrate accounting against hand counts and the paper's Table 2, and the PLY header arithmetic
against files written by plyfile."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from stgc.errors import DataError, FormatError
from stgc.eval.accounting import (
    MIB_TO_MBPS_PER_SECOND,
    bitstream_size,
    duration_seconds,
    mbps,
    measure_render_speed,
    mib,
    model_size,
    paper_model_bytes,
    ply_file_bytes,
    size_of_saved_model,
    speed_from_times,
    training_seconds,
)
from stgc.model.layout import ply_fields
from stgc.run import Run

# Paper Table 2 (Mirror, 1-s models): #Gaussians, "MB", Mbps.
PAPER_TABLE2 = [
    (433_936, 62.9, 527.68),
    (204_371, 29.62, 248.53),
    (199_736, 28.95, 242.89),
    (164_985, 23.91, 200.64),
    (141_714, 20.54, 172.34),
    (124_224, 18.01, 151.07),
]


def test_hand_count_full_model() -> None:
    # 433,936 Gaussians x 38 float32 = 65,958,272 bytes = 62.90 MiB; 1-s model.
    size = model_size(433_936, "full", duration_s=1.0)
    assert size.size_bytes == 433_936 * 38 * 4 == 65_958_272
    assert round(size.size_mib, 2) == 62.90
    assert size.mbps == pytest.approx(65_958_272 * 8 / 1e6)
    assert round(size.mbps, 2) == 527.67
    assert size.mbps == pytest.approx(size.size_mib * MIB_TO_MBPS_PER_SECOND)
    assert MIB_TO_MBPS_PER_SECOND == 8.388608
    assert model_size(10, "lite", 1.0).size_bytes == 1280
    # The decoder's 90 float32 weights count too.
    assert paper_model_bytes(1, "full", decoder_floats=90) == 152 + 360


@pytest.mark.parametrize("count,paper_mb,paper_mbps", PAPER_TABLE2)
def test_paper_table2_is_reproduced(count: int, paper_mb: float, paper_mbps: float) -> None:
    rows = paper_model_bytes(count, "full", decoder_floats=90)
    assert abs(mib(rows) - paper_mb) <= 0.01
    # Rows only are 0.01-0.02 Mbps short of the paper on every line ...
    assert 0.0 < paper_mbps - mbps(rows, 1.0) < 0.025
    # ... and the files (PLY with its header + a ~1 KB decoder .pt) reproduce every printed value exactly.
    files = ply_file_bytes(count, "full") + 1000
    assert round(mbps(files, 1.0), 2) == paper_mbps


@pytest.mark.parametrize("variant", ["full", "lite"])
def test_ply_file_bytes_matches_plyfile(tmp_path: Path, variant: str) -> None:
    names = ply_fields(variant)
    n = 17
    rows = np.zeros(n, dtype=[(name, "f4") for name in names])
    path = tmp_path / "point_cloud.ply"
    PlyData([PlyElement.describe(rows, "vertex")]).write(str(path))
    assert path.stat().st_size == ply_file_bytes(n, variant)


def test_size_of_saved_model_reads_run_dir(tmp_path: Path) -> None:
    names = ply_fields("full")
    for it, n in ((100, 5), (300, 11)):
        d = tmp_path / "point_cloud" / f"iteration_{it}"
        d.mkdir(parents=True)
        rows = np.zeros(n, dtype=[(name, "f4") for name in names])
        PlyData([PlyElement.describe(rows, "vertex")]).write(str(d / "point_cloud.ply"))
    state = {"mlp1.weight": torch.zeros(6, 12, 1, 1), "mlp2.weight": torch.zeros(3, 6, 1, 1)}
    torch.save(state, tmp_path / "point_cloud" / "iteration_300" / "point_cloud.pt")
    size = size_of_saved_model(tmp_path, duration_s=0.5)
    assert size.num_gaussians == 11 and size.variant == "full" and size.decoder_floats == 90
    assert size.size_bytes == 11 * 152 + 360
    assert size.mbps == pytest.approx((11 * 152 + 360) * 8 / 1e6 / 0.5)
    assert size.file_bytes["point_cloud.ply"] == ply_file_bytes(11, "full")
    assert size.files_total_bytes > size.size_bytes
    d = size.as_dict()
    assert d["size_mb"] == d["size_mib"] and d["size_mb_si"] == pytest.approx(size.size_bytes / 1e6)
    json.dumps(d)


def test_bad_inputs_name_the_file(tmp_path: Path) -> None:
    with pytest.raises(DataError, match="no point_cloud"):
        size_of_saved_model(tmp_path, 1.0)
    bad = tmp_path / "x.ply"
    bad.write_bytes(b"not a ply\n")
    with pytest.raises(FormatError, match="x.ply"):
        size_of_saved_model(bad, 1.0)
    other = tmp_path / "other.ply"
    PlyData([PlyElement.describe(np.zeros(2, dtype=[("x", "f4")]), "vertex")]).write(str(other))
    with pytest.raises(FormatError, match="official STG"):
        size_of_saved_model(other, 1.0)
    with pytest.raises(DataError):
        bitstream_size(tmp_path / "missing.stgc", 1, "full", 1.0)


def test_bitstream_size_is_the_file_size(tmp_path: Path) -> None:
    f = tmp_path / "model_q5.stgc"
    f.write_bytes(b"\0" * 12345)
    size = bitstream_size(f, 1000, "full", duration_s=duration_seconds(30, 30.0))
    assert size.size_bytes == 12345 and size.convention == "file"
    assert size.mbps == pytest.approx(12345 * 8 / 1e6)


def test_durations_and_speed() -> None:
    assert duration_seconds(50, 30.0) == pytest.approx(50 / 30)
    with pytest.raises(ValueError):
        duration_seconds(0, 30.0)
    s = speed_from_times([1.0, 1.0, 0.1, 0.3], warmup=2)
    assert s is not None and s.fps == pytest.approx(5.0) and s.frames_timed == 2
    assert speed_from_times([0.5], warmup=1) is None
    calls: list[int] = []
    speed = measure_render_speed(calls.append, [1, 2, 3], warmup=2, passes=2)
    assert calls == [1, 2, 1, 2, 3, 1, 2, 3] and speed.frames_timed == 6 and math.isfinite(speed.mean_ms)


def test_train_summary(tmp_path: Path) -> None:
    run = Run(tmp_path)
    assert run.read_summary() is None and not run.training_finished()
    (tmp_path / "train_summary.json").write_text(json.dumps({"wall_seconds": 12.5, "finished": True}))
    assert training_seconds(run.read_summary()) == 12.5 and run.training_finished()
    (tmp_path / "train_summary.json").write_text("{broken")
    with pytest.raises(FormatError, match="train_summary.json"):
        run.read_summary()
    assert not run.training_finished()  # a damaged summary is not trusted to say finished
