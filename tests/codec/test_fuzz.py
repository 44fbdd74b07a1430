"""Hostile input: seeded random mutations and truncations of valid files must each end in a clean FormatError
naming the file, or a valid model; never another exception, a crash, or a large allocation.

Raw mutations are mostly caught by the CRCs, so half of the cases re-seal the file after mutating (the way
docs/stgc-format.md defines it: payload sizes follow inserted and deleted bytes, then every checksum): those reach
the structural checks behind the checksums. Every attribute section, the decoder and the metadata are zstd frames,
which a changed byte breaks, so the content-level cases decompress a section, mutate what it holds (codes, flags,
depth, quantizers, prediction coefficients, the decoder's manifest, the metadata's JSON) and store it again,
recompressed or stored: those reach the checks on decoded content. Fuzzed: a full and a lite file of today's
encoder and version 2 and 3 reference files (tests/codec/reference)."""

from __future__ import annotations

import re
import struct
import tracemalloc
import zlib
from pathlib import Path

import numpy as np
import pytest
import zstandard

from stgc.codec import decode, encode
from stgc.codec.format import DecodedModel, decode_metadata
from stgc.codec.synthetic import synthetic_model
from stgc.errors import FormatError

CASES = 1200  # raw / resealed mutations of today's full file; the other files get OTHER_CASES each
OTHER_CASES = 120
CONTENT_CASES = 240  # content-level mutations per file
MEMORY_SAMPLE = 3  # one content case in 3 runs under tracemalloc (every raw and resealed case does)
MEMORY_LIMIT = 32 << 20  # a 500-Gaussian file decodes in well under 1 MB; nothing may claim more than this
SOURCE = "fuzzed.stgc"  # the name every FormatError must carry
REFERENCE = Path(__file__).parent / "reference"
# + one that compress_run wrote (a META section; 18-bit delta-coded positions, 4-byte codes)
REFERENCE_FILES = ("v2_full_q3", "v2_lite_q3", "v3_full_q3", "v3_lite_q3", "v2_lite_q5_meta")

# Layout from docs/stgc-format.md (kept separate from the codec's own structs on purpose).
HEADER = struct.Struct("<8sHBBIHHII")
ENTRY = struct.Struct("<4sBBBBIII")  # tag codec bits components flags raw_size payload_size payload_crc
QPARAM = struct.Struct("<dq")
QPARAM_SIZE = QPARAM.size
DELTA, INTERLEAVE, CENTRED, PREDICT = 1, 2, 4, 8  # section flags; PREDICT: C(C-1)/2 int16 coefficients follow
STORED, ZSTD = 0, 1


def entry_size(entry) -> int:
    comps, flags = entry[3], entry[4]
    return ENTRY.size + comps * QPARAM_SIZE + (comps * (comps - 1) if flags & PREDICT else 0)


def _resize_payloads(data: bytearray, table_end: int, num_sections: int, edit: tuple[int, int, int]) -> None:
    """Payload sizes after `edit` (at, removed, inserted) replaced bytes [at, at + removed) of the payloads by
    `inserted` bytes: each section loses what was removed from it and the one the insertion falls in grows."""
    at, removed, inserted = edit
    pos, start = 32, table_end
    for k in range(num_sections):
        if pos + ENTRY.size > table_end:
            break
        entry = list(ENTRY.unpack_from(data, pos))
        size = entry[6]
        end = start + size
        new = size - max(0, min(end, at + removed) - max(start, at))
        if start <= at < end or (k == num_sections - 1 and at >= end):
            new += inserted
        entry[6] = new
        if entry[1] == STORED:
            entry[5] = new  # a stored section's raw size is its payload size
        ENTRY.pack_into(data, pos, *entry)
        pos += entry_size(entry)
        start = end


def reseal(data: bytearray, edit: tuple[int, int, int] | None = None) -> bytearray:
    """Make a (possibly mutated) file consistent again wherever its structure allows: after `edit` (at, removed,
    inserted), the table size or the payload sizes it changed; then the section, table and header CRC32s."""
    if len(data) < 32:
        return data
    fields = list(HEADER.unpack_from(data))
    num_sections, table_size = fields[5], fields[7]
    if edit is not None and edit[0] >= 32:
        at, removed, inserted = edit
        if at + removed <= 32 + table_size and (removed or at < 32 + table_size):  # inside the section table
            table_size = fields[7] = max(0, table_size + inserted - removed)
        elif at >= 32 + table_size:  # inside the payloads
            _resize_payloads(data, 32 + table_size, num_sections, edit)
    table_end = 32 + table_size
    if table_end <= len(data):
        pos, payload = 32, table_end
        for _ in range(num_sections):
            if pos + ENTRY.size > table_end:
                break
            entry = list(ENTRY.unpack_from(data, pos))
            size = entry[6]
            if payload + size <= len(data):
                entry[7] = zlib.crc32(bytes(data[payload: payload + size]))
                ENTRY.pack_into(data, pos, *entry)
            payload += size
            pos += entry_size(entry)
        fields[8] = zlib.crc32(bytes(data[32:table_end]))
    HEADER.pack_into(data, 0, *fields)
    struct.pack_into("<I", data, 28, zlib.crc32(bytes(data[:28])))
    return data


def mutate(rng: np.random.Generator, data: bytes, table_end: int) -> tuple[bytearray, tuple[int, int, int] | None]:
    """A raw mutation, and the edit (at, removed, inserted) for those that move bytes (else None)."""
    out = bytearray(data)
    kind = rng.integers(0, 7)
    edit = None
    if kind == 0:  # flip a few bits anywhere
        for _ in range(rng.integers(1, 6)):
            out[rng.integers(0, len(out))] ^= 1 << rng.integers(0, 8)
    elif kind == 1:  # overwrite bytes of the header / section table (counts, sizes, bit depths, quantizers)
        for _ in range(rng.integers(1, 4)):
            out[rng.integers(8, table_end)] = rng.integers(0, 256)
    elif kind == 2:  # an extreme value in a header or table integer
        pos = int(rng.integers(8, table_end - 4))
        out[pos: pos + 4] = struct.pack("<I", int(rng.choice([0, 1, 2**31 - 1, 2**32 - 1, 2**27, 10**6])))
    elif kind == 3:  # truncate
        at = int(rng.integers(0, len(out)))
        edit = (at, len(out) - at, 0)
        del out[at:]
    elif kind == 4:  # append or insert junk
        at = int(rng.integers(0, len(out) + 1))
        junk = rng.integers(0, 256, int(rng.integers(1, 40))).astype(np.uint8).tobytes()
        edit = (at, 0, len(junk))
        out[at:at] = junk
    elif kind == 5:  # delete a slice
        a = int(rng.integers(0, len(out)))
        n = min(int(rng.integers(1, 64)), len(out) - a)
        edit = (a, n, 0)
        del out[a: a + n]
    else:  # scribble over a payload stretch
        a = int(rng.integers(table_end, len(out)))
        n = int(rng.integers(1, 16))
        out[a: a + n] = rng.integers(0, 256, len(out[a: a + n])).astype(np.uint8).tobytes()
    return out, edit


# ---------------------------------------------------------------------------------------- content-level mutations
class Section:
    """One section as a content mutation sees it: its table entry, the quantizer / coefficient bytes after the
    entry, and its decompressed content; `payload` keeps the stored bytes until the content is changed."""

    def __init__(self, entry: list, extra: bytes, payload: bytes):
        self.entry, self.extra, self.payload = entry, bytearray(extra), payload
        self.raw = bytearray(zstandard.ZstdDecompressor().decompress(payload) if entry[1] == ZSTD else payload)
        self.changed = False

    def copy(self) -> Section:
        out = Section.__new__(Section)
        out.entry, out.extra, out.payload = list(self.entry), bytearray(self.extra), self.payload
        out.raw, out.changed = bytearray(self.raw), self.changed
        return out


def split(data: bytes) -> tuple[list, list[Section]]:
    fields = list(HEADER.unpack_from(data))
    pos, offset = 32, 32 + fields[7]
    sections = []
    for _ in range(fields[5]):
        entry = list(ENTRY.unpack_from(data, pos))
        size = entry_size(entry)
        sections.append(Section(entry, data[pos + ENTRY.size: pos + size], data[offset: offset + entry[6]]))
        pos += size
        offset += entry[6]
    return fields, sections


def join(fields: list, sections: list[Section], rng: np.random.Generator) -> bytes:
    """The file again, every size and checksum right: a changed section is recompressed or stored (codec 0)."""
    table, payloads = bytearray(), []
    for sec in sections:
        entry = list(sec.entry)
        if sec.changed:
            if rng.random() < 0.5:
                entry[1], payload = STORED, bytes(sec.raw)
            else:
                entry[1], payload = ZSTD, zstandard.ZstdCompressor(level=1).compress(bytes(sec.raw))
            entry[5] = len(sec.raw)
        else:
            payload = sec.payload
        entry[6], entry[7] = len(payload), zlib.crc32(payload)
        table += ENTRY.pack(*entry) + sec.extra
        payloads.append(payload)
    fields = list(fields)
    fields[5], fields[7], fields[8] = len(sections), len(table), zlib.crc32(bytes(table))
    head = HEADER.pack(*fields)
    return head + struct.pack("<I", zlib.crc32(head)) + bytes(table) + b"".join(payloads)


_EXTREME_STEPS = (0.0, -1.0, float("inf"), float("nan"), 1e300, 5e-324, 1e-30, 3.4e38, 1.0)
_EXTREME_ZEROS = (0, -1, 2**53, -(2**53), 2**53 + 1, 2**63 - 1, -(2**63), 1 << 40)


def mutate_content(rng: np.random.Generator, sections: list[Section]) -> str:
    """Change one section's content or description in place; returns what was done (for failure messages)."""
    sec = sections[int(rng.integers(len(sections)))]
    tag, comps = sec.entry[0].decode("latin-1"), sec.entry[3]
    raw = sec.raw
    sec.changed = True
    kind = int(rng.integers(0, 8))
    if kind == 0 and raw:  # a few bytes of the content (in DECO mostly its manifest: counts, dtypes, shapes)
        head = 64 if tag == "DECO" and rng.random() < 0.5 else len(raw)
        for _ in range(rng.integers(1, 8)):
            raw[rng.integers(min(head, len(raw)))] = int(rng.integers(256))
        return f"{tag}: bytes"
    if kind == 1 and raw:  # a run of all-ones or zero bytes (codes at and beyond the top of their range)
        a = int(rng.integers(len(raw)))
        n = int(rng.integers(1, 64))
        raw[a: a + n] = bytes([int(rng.choice([0, 255]))]) * len(raw[a: a + n])
        return f"{tag}: run at {a}"
    if kind == 2 and comps:  # an extreme quantizer
        c = int(rng.integers(comps))
        step, zero = QPARAM.unpack_from(sec.extra, c * QPARAM_SIZE)
        if rng.random() < 0.5:
            step = float(rng.choice(_EXTREME_STEPS))
        else:
            zero = int(rng.choice(_EXTREME_ZEROS))
        QPARAM.pack_into(sec.extra, c * QPARAM_SIZE, step, zero)
        return f"{tag}: quantizer {c} = {step!r}, {zero}"
    if kind == 3 and sec.entry[4] & PREDICT and comps > 1:  # prediction coefficients
        k = int(rng.integers(comps * (comps - 1) // 2))
        value = int(rng.choice([-32768, 32767, 0, 256, int(rng.integers(-32768, 32768))]))
        struct.pack_into("<h", sec.extra, comps * QPARAM_SIZE + 2 * k, value)
        return f"{tag}: coefficient {k} = {value}"
    if kind == 4:  # toggle a flag; PREDICT brings or takes its coefficients with it, so the table still parses
        flag = int(rng.choice([DELTA, INTERLEAVE, CENTRED, PREDICT, 16]))
        sec.entry[4] ^= flag
        if flag == PREDICT and comps:
            count = comps * (comps - 1) // 2
            if sec.entry[4] & PREDICT:
                sec.extra += struct.pack(f"<{count}h", *rng.integers(-600, 600, count).tolist())
            else:
                del sec.extra[comps * QPARAM_SIZE:]
        return f"{tag}: flags ^= {flag}"
    if kind == 5:  # another depth, mostly one of the same code width (the sizes still agree: the codes decide)
        bits = sec.entry[2]
        if rng.random() < 0.8 and 2 <= bits <= 24:
            lo, hi = (2, 8) if bits <= 8 else (9, 16) if bits <= 16 else (17, 24)
            sec.entry[2] = int(rng.integers(lo, hi + 1))
        else:
            sec.entry[2] = int(rng.choice([0, 1, 25, 32, 255]))
        return f"{tag}: bits {bits} -> {sec.entry[2]}"
    if kind == 6:  # content shorter or longer than the table says it should be
        if raw and rng.random() < 0.5:
            del raw[int(rng.integers(len(raw))):]
        else:
            raw += rng.integers(0, 256, int(rng.integers(1, 9))).astype(np.uint8).tobytes()
        return f"{tag}: {len(raw)} raw bytes"
    # JSON or decoder values that parse but lie (a metadata value of another type, a non-finite weight)
    if tag == "META":
        sec.raw = bytearray(rng.choice([b"[]", b"{}", b'{"iteration": -1}', b'{"iteration": 1e999}', b"null",
                                        b'{"decoder_activation": 7, "run_config": []}', b'{"a": NaN}']))
    elif raw:
        a = int(rng.integers(len(raw) - 1)) if len(raw) > 1 else 0
        raw[a: a + 2] = rng.choice([b"\x00\x7c", b"\x00\xfe", b"\xff\x7f"])  # float16 inf / nan bytes
    return f"{tag}: values"


# --------------------------------------------------------------------------------------------------- the files
def _today(variant: str) -> bytes:
    n, seed = (500, 5) if variant == "full" else (300, 6)  # large enough for delta-coded positions
    arrays, decoder = synthetic_model(n, variant, seed=seed)
    return encode(arrays, variant, decoder, metadata={"iteration": 7, "scene_extent": 2.5})


FUZZED = ("v4_full_today", "v4_lite_today", *REFERENCE_FILES)


@pytest.fixture(scope="module")
def fuzzed_files() -> dict[str, bytes]:
    files = {"v4_full_today": _today("full"), "v4_lite_today": _today("lite")}
    files.update({name: (REFERENCE / f"{name}.stgc").read_bytes() for name in REFERENCE_FILES})
    return files


@pytest.fixture(scope="module")
def valid_file(fuzzed_files) -> tuple[bytes, int]:
    data = fuzzed_files["v4_full_today"]
    return data, 32 + HEADER.unpack_from(data)[7]


def _check_valid(model: DecodedModel) -> None:
    assert model.num_gaussians == len(model.arrays["x"]) <= 1 << 27
    for value in model.arrays.values():
        assert value.dtype == np.float32 and np.all(np.isfinite(value))
    for value in (model.decoder_state or {}).values():
        assert np.all(np.isfinite(value))


def _outcome(data: bytes, what: str) -> str | None:
    """Decode hostile bytes: None for a valid model, else the FormatError's problem. Anything else (another
    exception, an error that does not name the file, a bad model) fails the test; and, while tracemalloc traces,
    an allocation over the limit."""
    tracing = tracemalloc.is_tracing()
    if tracing:
        tracemalloc.reset_peak()
    try:  # the metadata alone (how a file names its run): a FormatError at worst, like the whole decode
        metadata = decode_metadata(data, source=SOURCE)
    except FormatError as exc:
        assert exc.path == Path(SOURCE), f"{what}: {exc} does not name the file"
        metadata = None
    try:
        model = decode(data, source=SOURCE)
    except FormatError as exc:
        assert exc.path == Path(SOURCE), f"{what}: {exc} does not name the file"
        problem = exc.problem
    else:
        _check_valid(model)
        assert metadata == model.metadata, what
        problem = None
    if tracing:
        peak = tracemalloc.get_traced_memory()[1]
        assert peak < MEMORY_LIMIT, f"{what}: decoding allocated {peak} bytes"
    return problem


def test_unmodified_files_decode(fuzzed_files):
    for name, data in fuzzed_files.items():
        _check_valid(decode(data))
    # The mutations below only reach the layouts these files use: delta, centred, predicted sections among them.
    flags = [e[4] for data in fuzzed_files.values() for _, e in _entries(data)]
    assert any(f & DELTA for f in flags) and any(f & CENTRED for f in flags) and any(f & PREDICT for f in flags)
    assert {decode(d).variant for d in fuzzed_files.values()} == {"full", "lite"}
    assert {HEADER.unpack_from(d)[1] for d in fuzzed_files.values()} == {2, 3, 4}


def _check_kind(problem: str) -> str:
    """Which check a problem comes from: its text without the numbers, tags and details that vary."""
    return re.sub(r"'[^']*'|-?\d+(\.\d+)?(e[+-]?\d+)?|\([^)]*\)", "#", problem)


def _is_file_length(problem: str) -> bool:
    """The check that the payload sizes add up to the file's length (spec §6, rule 2)."""
    return re.match(r"file (truncated|has trailing bytes)", problem) is not None


@pytest.mark.parametrize("name", FUZZED)
def test_random_mutations_end_in_format_error_or_a_valid_model(fuzzed_files, name):
    data = fuzzed_files[name]
    table_end = 32 + HEADER.unpack_from(data)[7]
    cases = CASES if name == "v4_full_today" else OTHER_CASES
    rng = np.random.default_rng([20251122, FUZZED.index(name)])
    outcomes = {"error": 0, "valid": 0}
    reasons = set()
    moved = stopped_at_length = 0  # resealed cases that insert, delete or truncate; those the file length stops
    tracemalloc.start()
    try:
        for case in range(cases):
            mutated, edit = mutate(rng, data, table_end)
            if case % 2:
                mutated = reseal(mutated, edit)
            problem = _outcome(bytes(mutated), f"{name} case {case}")
            outcomes["valid" if problem is None else "error"] += 1
            if problem is not None:
                reasons.add(_check_kind(problem))
            if case % 2 and edit is not None:
                moved += 1
                stopped_at_length += problem is not None and _is_file_length(problem)
    finally:
        tracemalloc.stop()
    assert outcomes["error"] > cases // 2
    assert len(reasons) > (15 if cases >= 1000 else 8), sorted(reasons)  # many checks, not only the CRCs
    # Resealing follows inserted and deleted bytes: only an edit of the header itself, or a truncation inside the
    # section table, still ends at the file length check (without the size fix: every one of them).
    assert stopped_at_length < moved // 4, f"{stopped_at_length} of {moved} resealed edits stop at the file length"


@pytest.mark.parametrize("name", FUZZED)
def test_content_mutations_end_in_format_error_or_a_valid_model(fuzzed_files, name):
    """Mutate what a section holds after decompression and store it again, every size and CRC right: these reach
    the checks on codes, depths, flags, quantizers, coefficients, the decoder's manifest and the metadata."""
    fields, pristine = split(fuzzed_files[name])
    rng = np.random.default_rng([20251123, FUZZED.index(name)])
    outcomes = {"error": 0, "valid": 0}
    reasons = set()
    for case in range(CONTENT_CASES):
        sections = [sec.copy() for sec in pristine]
        what = mutate_content(rng, sections)
        data = join(fields, sections, rng)
        # Sizes and N stay consistent here, so allocations stay bounded by the table; tracing every case would
        # make this test 4x slower: one case in MEMORY_SAMPLE runs under the allocation limit.
        if case % MEMORY_SAMPLE == 0:
            tracemalloc.start()
        try:
            problem = _outcome(data, f"{name} case {case} ({what})")
        finally:
            tracemalloc.stop()
        outcomes["valid" if problem is None else "error"] += 1
        if problem is not None:
            assert "checksum" not in problem and not _is_file_length(problem), f"{what}: {problem}"
            reasons.add(_check_kind(problem))
    assert outcomes["error"] > CONTENT_CASES // 4 and outcomes["valid"] > CONTENT_CASES // 10, outcomes
    assert len(reasons) > 10, sorted(reasons)  # many different checks, not one


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda d: d.__setitem__(slice(0, 4), b"PLY\n"), "magic"),
        (lambda d: struct.pack_into("<H", d, 8, 99), "version 99"),
        (lambda d: struct.pack_into("<I", d, 12, 2**32 - 1), "Gaussians"),
        (lambda d: struct.pack_into("<I", d, 12, 10**6), "does not match"),
        (lambda d: d.__setitem__(10, 7), "variant"),
    ],
)
def test_specific_header_lies_are_named(valid_file, edit, message):
    mutated = bytearray(valid_file[0])
    edit(mutated)
    with pytest.raises(FormatError, match=message):
        decode(bytes(reseal(mutated)))


def test_truncation_and_checksums_are_reported(valid_file):
    data, table_end = valid_file
    with pytest.raises(FormatError, match="shorter than"):
        decode(data[:20])
    with pytest.raises(FormatError, match="truncated"):
        decode(data[:-1])
    with pytest.raises(FormatError, match="trailing"):
        decode(data + b"\0")
    corrupted = bytearray(data)
    corrupted[-3] ^= 0x10
    with pytest.raises(FormatError, match="checksum"):
        decode(bytes(corrupted))


def test_a_zstd_bomb_claim_is_refused_before_decompression(valid_file):
    """N = 2**27 with every section size made consistent with it: the table alone shows the frames cannot expand
    that far, so nothing is decompressed or allocated."""
    data, _ = valid_file
    mutated = bytearray(data)
    n = 1 << 27
    struct.pack_into("<I", mutated, 12, n)
    pos = 32
    for _ in range(HEADER.unpack_from(mutated)[5]):
        entry = list(ENTRY.unpack_from(mutated, pos))
        tag, bits, comps = entry[0], entry[2], entry[3]
        if tag not in (b"DECO", b"META"):
            entry[5] = n * comps * (1 if bits <= 8 else 2 if bits <= 16 else 4)
            ENTRY.pack_into(mutated, pos, *entry)
        pos += entry_size(entry)
    tracemalloc.start()
    try:
        with pytest.raises(FormatError, match="more than zstd can expand"):
            decode(bytes(reseal(mutated)))
        assert tracemalloc.get_traced_memory()[1] < MEMORY_LIMIT
    finally:
        tracemalloc.stop()


def _entries(data: bytes):
    """(table offset, unpacked entry) of every section."""
    num_sections = HEADER.unpack_from(data)[5]
    pos, out = 32, []
    for _ in range(num_sections):
        entry = ENTRY.unpack_from(data, pos)
        out.append((pos, list(entry)))
        pos += entry_size(entry)
    return out


def _set_flags(data: bytes, tag: bytes, flags: int) -> bytes:
    out = bytearray(data)
    for pos, entry in _entries(data):
        if entry[0] == tag:
            entry[4] = flags
            ENTRY.pack_into(out, pos, *entry)
    return bytes(reseal(out))


def test_centred_sections_are_checked(valid_file):
    data, _ = valid_file
    with pytest.raises(FormatError, match="combines centring"):
        decode(_set_flags(data, b"MOTN", 1 | 4))  # centring and delta
    with pytest.raises(FormatError, match="combines centring"):
        decode(_set_flags(data, b"ROTN", 4))  # quaternion indices are not centred
    # A plain 8-bit section read as centred needs a 9-bit (uint16) container: the sizes disagree.
    arrays, decoder = synthetic_model(500, "full", seed=5)
    eight = encode(arrays, "full", decoder, group_bits={"OPAC": 8})  # opacity: plain at any depth
    plain = next(e for _, e in _entries(eight) if e[0] == b"OPAC")
    assert plain[4] & 5 == 0 and plain[2] == 8
    with pytest.raises(FormatError, match="does not match"):
        decode(_set_flags(eight, plain[0], plain[4] | 4))


def test_predicted_sections_are_checked(valid_file):
    data, _ = valid_file
    predicted = next(e for _, e in _entries(data) if e[4] & PREDICT)
    with pytest.raises(FormatError, match="predicted without being centred"):
        decode(_set_flags(data, predicted[0], predicted[4] & ~4))
    # Without the flag the coefficients are unexplained table bytes.
    with pytest.raises(FormatError, match="trailing bytes|runs? past|does not match"):
        decode(_set_flags(data, predicted[0], predicted[4] & ~PREDICT))
