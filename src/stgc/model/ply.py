"""Reading and writing the official STG checkpoint: point_cloud.ply (+ point_cloud.pt decoder for `full`).

Arrays are exchanged as {official field name: float32 [N]} in `layout.ply_fields(variant)` order, normals included
(zeros), so the codec can treat a model as a table of named float32 columns.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import torch
from plyfile import PlyData, PlyElement, PlyElementParseError, PlyListProperty

from stgc.errors import FormatError
from stgc.fileio import atomic_open, atomic_path
from stgc.model.layout import NORMAL_FIELDS, ply_fields
from stgc.run import SAVED_MODEL, latest_iteration_dir

PLY_NAME = SAVED_MODEL
DECODER_NAME = "point_cloud.pt"
DECODER_SHAPES = {"mlp1.weight": (6, 12, 1, 1), "mlp2.weight": (3, 6, 1, 1)}


def detect_variant(field_names: list[str] | set[str], path: Path | None = None) -> str:
    """'full' or 'lite' from the PLY's field names; FormatError when it is neither."""
    names = set(field_names)
    for variant in ("full", "lite"):
        required = set(ply_fields(variant)) - set(NORMAL_FIELDS)
        if variant == "lite" and ({"f_dc_3", "f_t_0"} & names):
            continue
        if required <= names:
            return variant
    missing_full = sorted(set(ply_fields("full")) - set(NORMAL_FIELDS) - names, key=ply_fields("full").index)
    missing_lite = sorted(set(ply_fields("lite")) - set(NORMAL_FIELDS) - names, key=ply_fields("lite").index)
    # A file with full-only fields is a full model missing some, even where it holds all a lite model needs.
    missing = (missing_full if ({"f_dc_3", "f_t_0"} & names) or len(missing_full) <= len(missing_lite)
               else missing_lite)
    raise FormatError(path, f"not an STG point cloud: missing field(s) {', '.join(missing)}")


def validate_arrays(arrays: dict[str, np.ndarray], variant: str, path: Path | None = None) -> int:
    """Check presence, dtype, shape and finiteness of every non-normal field; return the number of Gaussians."""
    count = None
    for name in ply_fields(variant):
        if name in NORMAL_FIELDS:
            continue
        if name not in arrays:
            raise FormatError(path, f"missing field {name!r} for an STG {variant} model")
        column = np.asarray(arrays[name])
        if column.dtype != np.float32:
            raise FormatError(path, f"field {name!r} has dtype {column.dtype}, expected float32")
        if column.ndim != 1:
            raise FormatError(path, f"field {name!r} has shape {column.shape}, expected one value per Gaussian")
        if count is None:
            count = column.shape[0]
        elif column.shape[0] != count:
            raise FormatError(path, f"field {name!r} has {column.shape[0]} values, expected {count}")
        bad = int(np.count_nonzero(~np.isfinite(column)))
        if bad:
            raise FormatError(path, f"field {name!r} has {bad} non-finite value(s) (NaN or inf)")
    return int(count or 0)


def write_ply(path: str | Path, arrays: dict[str, np.ndarray], variant: str) -> None:
    """Binary little-endian float32 PLY with one 'vertex' element in the official field order, atomically."""
    names = ply_fields(variant)
    count = validate_arrays(arrays, variant, Path(path))
    rows = np.empty(count, dtype=[(name, "<f4") for name in names])
    for name in names:
        rows[name] = arrays[name] if name in arrays else 0.0
    with atomic_path(path) as tmp:
        PlyData([PlyElement.describe(rows, "vertex")], text=False, byte_order="<").write(str(tmp))


def read_ply(path: str | Path) -> tuple[dict[str, np.ndarray], str]:
    """(arrays, variant) of an STG PLY; FormatError for anything we cannot use as is."""
    path = Path(path)
    try:
        with open(path, "rb") as stream:
            ply = PlyData.read(stream)
            end, size = stream.tell(), os.fstat(stream.fileno()).st_size
    except FileNotFoundError:
        raise FormatError(path, "file not found") from None
    except PlyElementParseError as exc:
        if exc.message == "early end-of-file" and exc.element is not None and exc.row is not None:
            rows = "vertices" if exc.element.name == "vertex" else f"{exc.element.name!r} rows"
            raise FormatError(path, f"its header counts {exc.element.count} {rows} but its body holds only "
                                    f"{exc.row}: a truncated or damaged file") from None
        raise FormatError(path, f"not a readable PLY file ({type(exc).__name__}: {exc})") from None
    except Exception as exc:  # plyfile raises several types for malformed headers and bodies
        raise FormatError(path, f"not a readable PLY file ({type(exc).__name__}: {exc})") from None
    if "vertex" not in ply:
        raise FormatError(path, "PLY has no 'vertex' element")
    vertex = ply["vertex"]
    if not ply.text and end != size:
        _refuse_trailing_bytes(path, ply, size - end)
    names = [prop.name for prop in vertex.properties]
    variant = detect_variant(names, path)
    unknown = [name for name in names if name not in ply_fields(variant)]
    if unknown:
        # The official loader sizes its arrays from the fields present: a variant with more coefficients would be
        # rendered truncated here.
        raise FormatError(path, f"field(s) an STG {variant} model does not have: {', '.join(unknown)}")
    arrays = {name: np.asarray(vertex[name]) for name in ply_fields(variant) if name in names}
    for name in arrays:  # plyfile returns the file's byte order; keep native float32 in memory
        if arrays[name].dtype.kind == "f" and arrays[name].dtype.itemsize == 4:
            arrays[name] = arrays[name].astype(np.float32, copy=False)
    validate_arrays(arrays, variant, path)
    for name in NORMAL_FIELDS:
        arrays.setdefault(name, np.zeros(len(arrays["x"]), dtype=np.float32))
    return {name: arrays[name] for name in ply_fields(variant)}, variant


def _refuse_trailing_bytes(path: Path, ply: PlyData, extra: int) -> None:
    """FormatError for a binary PLY longer than its header says: plyfile reads the rows the header counts and
    ignores the rest, so a damaged count would load a prefix of the model."""
    vertex = ply["vertex"]
    if len(ply.elements) == 1 and not any(isinstance(prop, PlyListProperty) for prop in vertex.properties):
        row = vertex.dtype(ply.byte_order).itemsize
        rows = vertex.count + extra / row
        held = f"{rows:.0f}" if rows.is_integer() else f"{rows:.2f}"
        raise FormatError(path, f"its header counts {vertex.count} vertices but its body holds {held} (rows of "
                                f"{row} bytes): a damaged file")
    raise FormatError(path, f"{extra} byte(s) after the rows its header counts: a damaged file")


def write_decoder(path: str | Path, state: dict[str, torch.Tensor]) -> None:
    # Through a Python file, so that a failed write raises OSError with its cause (torch's own file writer only
    # says "iostream error").
    with atomic_open(path, "wb") as f:
        torch.save({key: value.detach().cpu().contiguous() for key, value in state.items()}, f)


def read_decoder(path: str | Path) -> dict[str, np.ndarray]:
    """The official decoder state_dict as float32 arrays in the official 1x1-conv shapes."""
    path = Path(path)
    if not path.is_file():
        raise FormatError(path, "missing: a full-variant point_cloud.ply needs its decoder weights beside it")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise FormatError(path, f"not a readable torch file ({type(exc).__name__}: {exc})") from None
    if not isinstance(state, dict):
        raise FormatError(path, f"expected a decoder state_dict, found {type(state).__name__}")
    return validate_decoder_state(state, path)


def validate_decoder_state(state: dict[str, Any], path: Path | None = None) -> dict[str, np.ndarray]:
    """The decoder's weights, in the official 1x1-convolution shapes; FormatError for any other key (a bias: the
    official decoder has none) or shape (as [out, in, 1, 1] or [out, in] only: a transposed matrix of the same size
    would be read scrambled)."""
    extra = sorted(set(state) - set(DECODER_SHAPES))
    if extra:
        raise FormatError(path, f"decoder state has key(s) STG's decoder does not have: {', '.join(map(str, extra))}")
    out = {}
    for key, shape in DECODER_SHAPES.items():
        if key not in state:
            raise FormatError(path, f"decoder state has no {key!r} (keys: {sorted(state)})")
        value = state[key]
        try:
            if torch.is_tensor(value):
                value = value.detach().cpu()
                # numpy has no bfloat16: floating tensors of every width become float32, the decoder's own width
                array = (value.float() if value.is_floating_point() else value).numpy()
            else:
                array = np.asarray(value)
        except (TypeError, ValueError, RuntimeError) as exc:
            raise FormatError(path, f"decoder {key!r} is not an array of numbers "
                                    f"({type(exc).__name__}: {exc})") from None
        if tuple(array.shape) not in (shape, shape[:2]):
            raise FormatError(path, f"decoder {key!r} has shape {tuple(array.shape)}, expected {shape}")
        if array.dtype.kind not in "iuf":  # complex, bool, strings, objects: no weights a float32 conv can take
            raise FormatError(path, f"decoder {key!r} holds {array.dtype} values, expected real numbers")
        array = array.astype(np.float32)
        if not np.all(np.isfinite(array)):
            raise FormatError(path, f"decoder {key!r} has non-finite values")
        out[key] = array.reshape(shape)
    return out


def resolve_ply_path(path: str | Path) -> Path:
    """point_cloud.ply from a .ply path, an iteration dir, or a run dir (its highest iteration)."""
    path = Path(path)
    if path.is_file():
        return path
    if not path.exists():
        raise FormatError(path, "no such file or directory")
    if (path / PLY_NAME).is_file():
        return path / PLY_NAME
    latest = latest_iteration_dir(path)
    if latest is None:
        raise FormatError(path, f"no {PLY_NAME} here nor under point_cloud/iteration_<N>/")
    return latest / PLY_NAME
