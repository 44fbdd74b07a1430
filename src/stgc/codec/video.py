"""The whole-video `.stgc` container: a video trained as consecutive segments, one file (docs/stgc-format.md §9).

The container holds each segment's own single-model `.stgc` bitstream unchanged, behind a small index of frame
ranges, offsets, lengths and checksums. A reader reads the header and index only, then seeks to the one segment it
needs (random access by time); every segment decodes on its own with `stgc.codec.decode`.
"""

from __future__ import annotations

import os
import struct
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from stgc.errors import DataError, FormatError

from .format import MAX_FILE_BYTES, VIDEO_MAGIC, DecodedModel, decode, decode_metadata, read_header

VIDEO_VERSION = 1
MAX_VIDEO_SEGMENTS = 4096
MAX_FRAME = 1 << 31  # frame indices are u32; keeping them below 2^31 leaves first_frame + num_frames in range

_VIDEO_HEADER = struct.Struct("<8sHHIIII")  # magic version flags num_segments index_size index_crc reserved
_VIDEO_HEADER_CRC = struct.Struct("<I")
VIDEO_HEADER_SIZE = _VIDEO_HEADER.size + _VIDEO_HEADER_CRC.size  # 32
_INDEX_ENTRY = struct.Struct("<IIQQII")  # first_frame num_frames offset length payload_crc reserved
INDEX_ENTRY_SIZE = _INDEX_ENTRY.size  # 32


@dataclass(frozen=True)
class VideoSegmentEntry:
    """One segment of a whole-video container: the frames it covers and where its bitstream lies."""

    first_frame: int
    num_frames: int
    offset: int
    length: int
    payload_crc: int

    @property
    def last_frame(self) -> int:
        return self.first_frame + self.num_frames - 1


@dataclass(frozen=True)
class VideoIndex:
    """Header and index of a whole-video container (no segment is decoded)."""

    entries: tuple[VideoSegmentEntry, ...]
    file_bytes: int

    @property
    def num_segments(self) -> int:
        return len(self.entries)

    @property
    def frames(self) -> range:
        return range(self.entries[0].first_frame, self.entries[-1].last_frame + 1)

    @property
    def overhead_bytes(self) -> int:
        """Bytes of the container itself (header and index), beyond its segments' bitstreams."""
        return VIDEO_HEADER_SIZE + INDEX_ENTRY_SIZE * len(self.entries)

    def segment_of_frame(self, frame: int) -> int:
        """Index of the segment holding absolute `frame`."""
        for k, entry in enumerate(self.entries):
            if entry.first_frame <= frame <= entry.last_frame:
                return k
        raise DataError(None, f"frame {frame} is outside the video's frames {self.frames.start}-{self.frames.stop - 1}")


def encode_video(segments: Sequence[tuple[int, int, bytes]]) -> bytes:
    """The container of consecutive segments, each given as (first_frame, num_frames, its .stgc bitstream)."""
    if not 1 <= len(segments) <= MAX_VIDEO_SEGMENTS:
        raise ValueError(f"a whole-video .stgc holds 1..{MAX_VIDEO_SEGMENTS} segments, not {len(segments)}")
    index = bytearray()
    offset = VIDEO_HEADER_SIZE + INDEX_ENTRY_SIZE * len(segments)
    expected_first = None
    for k, (first_frame, num_frames, payload) in enumerate(segments):
        if num_frames < 1 or not 0 <= first_frame < MAX_FRAME or first_frame + num_frames > MAX_FRAME:
            raise ValueError(f"segment frames {first_frame}+{num_frames} out of range")
        if expected_first is not None and first_frame != expected_first:
            raise ValueError(f"segments must be consecutive: one starts at frame {first_frame}, expected {expected_first}")
        # A container never carries a segment its reader would refuse.
        decode(payload, source=f"segment {k} (frames {first_frame}+{num_frames})")
        index += _INDEX_ENTRY.pack(first_frame, num_frames, offset, len(payload), zlib.crc32(payload), 0)
        offset += len(payload)
        expected_first = first_frame + num_frames
    header = _VIDEO_HEADER.pack(VIDEO_MAGIC, VIDEO_VERSION, 0, len(segments), len(index), zlib.crc32(index), 0)
    return b"".join([header, _VIDEO_HEADER_CRC.pack(zlib.crc32(header)), bytes(index), *(p for *_, p in segments)])


def _fail(problem: str, source: str | None) -> FormatError:
    return FormatError(source, problem)


def parse_video_index(head: bytes, file_bytes: int, source: str | None = None) -> VideoIndex:
    """Validate a container's header and index from its first bytes (`head`, at least header + index) and the
    file's total size; payloads are not read (their checksums are checked when a segment is read)."""
    if len(head) < VIDEO_HEADER_SIZE:
        raise _fail(f"not a whole-video .stgc: shorter than the {VIDEO_HEADER_SIZE}-byte header", source)
    magic, version, flags, count, index_size, index_crc, reserved = _VIDEO_HEADER.unpack_from(head)
    if magic != VIDEO_MAGIC:
        raise _fail("not a whole-video .stgc (bad magic bytes)", source)
    (header_crc,) = _VIDEO_HEADER_CRC.unpack_from(head, _VIDEO_HEADER.size)
    if zlib.crc32(head[: _VIDEO_HEADER.size]) != header_crc:
        raise _fail("header checksum mismatch (file corrupted)", source)
    if version != VIDEO_VERSION:
        raise _fail(f"unsupported whole-video .stgc version {version} (this reader knows {VIDEO_VERSION})", source)
    if flags != 0 or reserved != 0:
        raise _fail("unknown header flags or a non-zero reserved field", source)
    if not 1 <= count <= MAX_VIDEO_SEGMENTS:
        raise _fail(f"claims {count} segments, outside 1..{MAX_VIDEO_SEGMENTS}", source)
    if index_size != count * INDEX_ENTRY_SIZE:
        raise _fail(f"index of {index_size} bytes does not hold {count} entries of {INDEX_ENTRY_SIZE} bytes", source)
    if len(head) < VIDEO_HEADER_SIZE + index_size:
        raise _fail("the index runs past the end of the file (truncated?)", source)
    index = head[VIDEO_HEADER_SIZE: VIDEO_HEADER_SIZE + index_size]
    if zlib.crc32(index) != index_crc:
        raise _fail("index checksum mismatch (file corrupted)", source)
    entries = []
    offset = VIDEO_HEADER_SIZE + index_size
    next_frame = None
    for k in range(count):
        first, frames, at, length, crc, spare = _INDEX_ENTRY.unpack_from(index, k * INDEX_ENTRY_SIZE)
        where = f"segment {k}"
        if spare != 0:
            raise _fail(f"{where}: non-zero reserved field", source)
        if frames < 1 or first >= MAX_FRAME or first + frames > MAX_FRAME:
            raise _fail(f"{where}: frames {first}+{frames} out of range", source)
        if next_frame is not None and first != next_frame:
            raise _fail(f"{where}: starts at frame {first}, not where the previous one ends ({next_frame})", source)
        if at != offset:
            raise _fail(f"{where}: offset {at} is not where the previous segment ends ({offset})", source)
        if length < VIDEO_HEADER_SIZE or length > MAX_FILE_BYTES:
            raise _fail(f"{where}: length {length} is not that of a .stgc bitstream", source)
        entries.append(VideoSegmentEntry(first, frames, at, length, crc))
        offset += length
        next_frame = first + frames
    if offset > file_bytes:
        raise _fail(f"segments end at byte {offset}, past the end of the file ({file_bytes} bytes; truncated?)", source)
    if offset < file_bytes:
        raise _fail(f"{file_bytes - offset} trailing bytes after the last segment", source)
    return VideoIndex(tuple(entries), file_bytes)


def _checked_payload(payload: bytes, index: VideoIndex, k: int, source: str | None) -> bytes:
    entry = index.entries[k]
    if len(payload) != entry.length:
        raise _fail(f"segment {k}: truncated", source)
    if zlib.crc32(payload) != entry.payload_crc:
        raise _fail(f"segment {k}: checksum mismatch (file corrupted)", source)
    return payload


def decode_video(data: bytes, source: str | None = None) -> list[DecodedModel]:
    """Every segment of a container held in memory, decoded (any defect: FormatError)."""
    index = parse_video_index(data, len(data), source)
    return [decode(_checked_payload(data[e.offset: e.offset + e.length], index, k, source),
                   source=f"{source or 'bitstream'} segment {k}") for k, e in enumerate(index.entries)]


def is_video_stgc(path: str | os.PathLike) -> bool:
    """Whether `path` is a file starting with the whole-video container's magic (a cheap peek, no validation)."""
    if not Path(path).is_file():  # a pipe or a terminal would block the peek forever
        return False
    try:
        with open(path, "rb") as f:
            return f.read(len(VIDEO_MAGIC)) == VIDEO_MAGIC
    except OSError:
        return False


def read_video_index(path: str | os.PathLike) -> VideoIndex:
    """Header and index of a whole-video .stgc file, reading only their bytes."""
    path = Path(path)
    try:
        size = path.stat().st_size
        if not path.is_file():  # a device or a pipe says size 0 and may never end
            raise FormatError(path, "not a regular file")
        with open(path, "rb") as f:
            head = f.read(VIDEO_HEADER_SIZE)
            if len(head) == VIDEO_HEADER_SIZE and head[:8] == VIDEO_MAGIC:
                (index_size,) = struct.unpack_from("<I", head, 16)
                head += f.read(min(index_size, MAX_VIDEO_SEGMENTS * INDEX_ENTRY_SIZE))
    except OSError as exc:
        raise DataError(path, f"cannot read .stgc file ({exc.strerror})") from None
    return parse_video_index(head, size, str(path))


def read_video_segment(path: str | os.PathLike, k: int, index: VideoIndex | None = None) -> DecodedModel:
    """Segment `k` of a whole-video .stgc file, decoded; only its own bytes are read."""
    return decode(_segment_bytes(path, k, index), source=f"{path} segment {k}")


def read_video_segment_metadata(path: str | os.PathLike, k: int, index: VideoIndex | None = None) -> dict[str, Any]:
    """The metadata segment `k` of a whole-video .stgc file embeds, without decoding its Gaussians."""
    return decode_metadata(_segment_bytes(path, k, index), source=f"{path} segment {k}")


def _segment_bytes(path: str | os.PathLike, k: int, index: VideoIndex | None) -> bytes:
    """Segment `k`'s bitstream, checked against the index; only its own bytes are read."""
    path = Path(path)
    index = index or read_video_index(path)
    if not 0 <= k < index.num_segments:
        raise IndexError(f"{path}: segment {k} of {index.num_segments}")
    entry = index.entries[k]
    try:
        with open(path, "rb") as f:
            f.seek(entry.offset)
            payload = f.read(entry.length)
    except OSError as exc:
        raise DataError(path, f"cannot read .stgc file ({exc.strerror})") from None
    return _checked_payload(payload, index, k, str(path))
