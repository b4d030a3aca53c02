"""C3D files: their structure checked before `ezc3d` reads them (`c3d_layout`), and the reader
(`read_c3d`)."""

from __future__ import annotations

import math
import struct
from pathlib import Path

import numpy as np

from .._runtime.errors import InputError
from .markers import MarkerData, check_up_axis, fixed_markers
from .text import cut_short

#: C3D processor types (byte 4 of the parameter section): 84 Intel, 85 DEC (both little-endian
#: integers), 86 MIPS/SGI (big-endian)
_C3D_PROCESSORS = {84: "<", 85: "<", 86: ">"}


def c3d_layout(path) -> dict:
    """Check the structure of a C3D file before `ezc3d` reads it (ezc3d reads a truncated or
    corrupt file without a word, and on some corrupt parameter sections crashes or hangs): the
    512-byte header (key byte 0x50, parameter block, points, analog samples, first and last
    frame, scale, data start) and every record of the parameter section (names: printable ASCII,
    spaces allowed; types, dimensions, offsets inside the section). Any problem is an
    `InputError` naming the file. Returns `{"frames": the declared frame count or None (a header
    saturated at 65535), "frames_in_file", "points", "data_start": byte offset, "used":
    {"GROUP:NAME": value} of the scalar integer parameters (`ANALOG:USED`, ...)}`.
    """
    path = Path(path)
    source = str(path)
    raw = path.read_bytes()  # (the whole file: ezc3d reads it all too)
    size = len(raw)
    if size == 0:
        raise InputError(f"{source}: the file is empty (0 bytes), not a C3D file; export or copy it again.")
    if size < 512 or raw[1] != 0x50:
        what = (
            f"{size} bytes, shorter than the 512-byte header"
            if size < 512
            else f"its second byte is 0x{raw[1]:02x}, not 0x50"
        )
        raise InputError(f"{source}: not a C3D file ({what}); check the file (and --format: motive, vicon or c3d).")
    p0 = (raw[0] - 1) * 512
    if raw[0] < 2 or size < p0 + 4:
        raise InputError(
            f"{source}: the C3D file is cut short or corrupt: its parameter section (block {raw[0]}) is not in the "
            f"file ({size} bytes); export or copy it again."
        )
    head = raw[p0 : p0 + 4]
    endian = _C3D_PROCESSORS.get(head[3])
    if endian is None:
        raise InputError(f"{source}: not a C3D file, or a corrupt one (processor type {head[3]}, not 84, 85 or 86).")
    n_points, n_analog, first, last = struct.unpack(endian + "4H", raw[2:10])
    data_start = struct.unpack(endian + "H", raw[16:18])[0]
    sign_byte = {">": 12, "<": 15}[endian] if head[3] != 85 else 13  # the sign bit of the scale factor
    float_data = bool(raw[sign_byte] & 0x80)
    p_end = p0 + 512 * head[2]
    if head[2] == 0 or data_start - 1 < raw[0] or size < p_end:
        raise InputError(
            f"{source}: the C3D file is cut short or corrupt: {size} bytes, but its parameters end at byte {p_end} and its "
            f"data start at byte {512 * (data_start - 1)}; export or copy it again."
        )
    used = _check_c3d_parameters(raw[p0:p_end], endian, source)
    frame_bytes = (4 * n_points + n_analog) * (4 if float_data else 2)
    start = 512 * (data_start - 1)
    if size < start:
        raise InputError(f"{source}: the C3D file is cut short before its data (byte {start}; the file has {size}).")
    frames = last - first + 1 if (last >= first and last < 65535) else None
    in_file = (size - start) // frame_bytes if frame_bytes else (frames or 0)
    return {"frames": frames, "frames_in_file": int(in_file), "points": n_points, "data_start": start, "used": used}


def _check_c3d_parameters(params: bytes, endian: str, source: str) -> dict[str, int]:
    """Walk the records of a C3D parameter section (`params`: the whole section, from its 4-byte
    head); raise `InputError` at the first that runs out of the section or makes no sense.
    Returns `{"GROUP:NAME": value}` of its scalar integer parameters."""
    pos, n_records = 4, 0
    end = len(params)
    groups: dict[int, str] = {}
    scalars: dict[tuple[int, str], int] = {}

    def found() -> dict[str, int]:
        return {f"{groups.get(g, '?')}:{name}": v for (g, name), v in scalars.items()}

    def bad(why: str):
        return InputError(
            f"{source}: the C3D file is corrupt: parameter record {n_records + 1} ({why}); export or copy it again."
        )

    while pos + 2 <= end:
        n_name = abs(struct.unpack("b", params[pos : pos + 1])[0])
        if n_name == 0:
            return found()  # the end of the records
        name = params[pos + 2 : pos + 2 + n_name]
        # printable ASCII; spaces inside a name (QTM: "Uncropped Measurement Length"), not before it
        if len(name) < n_name or not all(32 <= c < 127 for c in name) or name[0] == 32:
            raise bad("its name is not printable")
        gid = struct.unpack("b", params[pos + 1 : pos + 2])[0]
        group = gid < 0
        if group:
            groups[-gid] = name.decode("ascii").upper()
        at = pos + 2 + n_name  # the offset to the next record counts from here
        if at + 2 > end:
            raise bad("it runs past the section")
        nxt = struct.unpack(endian + "h", params[at : at + 2])[0]
        q = at + 2
        if not group:
            if q + 2 > end:
                raise bad("it runs past the section")
            typ, ndim = struct.unpack("b", params[q : q + 1])[0], params[q + 1]
            if typ not in (-1, 1, 2, 4) or ndim > 7:
                raise bad(f"type {typ}, {ndim} dimensions")
            dims = params[q + 2 : q + 2 + ndim]
            if typ == 2 and ndim == 0 and q + 4 <= end:
                scalars[(gid, name.decode("ascii").upper())] = struct.unpack(endian + "h", params[q + 2 : q + 4])[0]
            q += 2 + ndim + abs(typ) * int(np.prod(list(dims), dtype=np.int64))
        if q + 1 > end or q + 1 + params[q] > end:
            raise bad("it runs past the section")
        if nxt == 0:
            return found()  # the last record
        if nxt < 0 or at + nxt <= pos or at + nxt > end:
            raise bad(f"its link to the next record ({nxt}) leaves the section")
        pos = at + nxt
        n_records += 1
        if n_records > 100_000:
            raise bad("too many records")
    return found()


def _other_data(layout: dict) -> str:
    """What a C3D file without points holds instead, in words, from its `*:USED` parameters."""
    used = layout["used"]
    what = [
        f"{n} {word}{'s' if n != 1 else ''}"
        for key, word in (
            ("ANALOG:USED", "analog channel"),
            ("FORCE_PLATFORM:USED", "force plate"),
            ("ROTATION:USED", "rotation"),
        )
        if (n := used.get(key, 0)) > 0
    ]
    return f"only {', '.join(what)}" if what else "no other data"


def read_c3d(path, *, units: str = "auto", up_axis: str = "z", allow_truncated: bool = False) -> MarkerData:
    """Read marker trajectories from a C3D file through `ezc3d` (`pip install -e ".[c3d]"` in the
    jsphere source folder): `POINT:LABELS`, `POINT:RATE`, `POINT:UNITS` and `data.points` `(4, K,
    M)`, a point whose residual is negative a gap; times are frame / rate from 0. The structure
    is checked first (`c3d_layout`); a file with no points is an `InputError` saying what it
    holds. `allow_truncated`: as in `ConvertOptions` (fewer frames than the header declares).
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"capture file {path} does not exist.")
    source = str(path)
    check_up_axis(up_axis, source)
    layout = c3d_layout(path)
    if layout["points"] == 0:
        raise InputError(
            f"{source}: the C3D file holds no marker trajectories (its header declares 0 points; {_other_data(layout)}); "
            "jsphere converts marker trajectories: export the take's markers (3D point data) to C3D."
        )
    declared, present = layout["frames"], layout["frames_in_file"]
    if declared is not None and present < declared:
        what = f"the header declares {declared} frames but the file holds {present}"
        cut_short(source, what, present, "frames present", allow_truncated)
    try:  # after the checks of the file's structure, which need no ezc3d
        import ezc3d
    except ImportError:
        raise ImportError(
            'read_c3d needs the optional dependency ezc3d: pip install ezc3d (or pip install -e ".[c3d]" in the jsphere source folder).'
        ) from None
    try:
        c = ezc3d.c3d(str(path))
        point = c["parameters"]["POINT"]
        labels = tuple(str(s).strip() for s in point["LABELS"]["value"])
        rate = float(point["RATE"]["value"][0])
        file_units = str(point["UNITS"]["value"][0]).strip() if len(point.get("UNITS", {}).get("value", ())) else None
        pts = np.asarray(c["data"]["points"], float)
        res = np.asarray(c["data"]["meta_points"]["residuals"], float)
    except (RuntimeError, OSError, ValueError, KeyError, IndexError, TypeError) as e:
        raise InputError(
            f"{source}: not a readable C3D file (ezc3d: {str(e).strip() or type(e).__name__}); export it again."
        ) from None
    if not (math.isfinite(rate) and rate > 0):
        raise InputError(f"{source}: POINT:RATE is {rate:g}; the frame rate must be a positive number of Hz.")
    if file_units not in (None, "m", "mm"):
        raise ValueError(f"{source}: POINT:UNITS is {file_units!r}; only 'm' and 'mm' are supported.")
    if (
        pts.ndim != 3
        or pts.shape[0] < 3
        or pts.shape[1] != len(labels)
        or res.ndim != 3
        or res.shape[1:] != pts.shape[1:]
    ):
        raise ValueError(f"{source}: data.points has shape {pts.shape}; expected (4, {len(labels)}, frames).")
    if pts.shape[2] == 0:
        raise InputError(f"{source}: the C3D file holds no frames.")
    raw = np.transpose(pts[:3], (2, 1, 0)).copy()  # (M, K, 3)
    raw[res[0].T < 0] = np.nan
    t = np.arange(raw.shape[0]) / rate
    markers, _ = fixed_markers(raw, source, units, file_units, up_axis)
    return MarkerData(t, markers, labels, source, None)
