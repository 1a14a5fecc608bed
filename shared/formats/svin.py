"""Trajectory text as SLAM systems write it: TUM, SVIn2 and OKVIS, stamps read exactly.

One reader for the pose files of visual-inertial SLAM systems, beside
`shared.formats.tum` (which reads and writes our own TUM files, strictly):

* **TUM** (`timestamp tx ty tz qx qy qz qw`, whitespace or commas): the stamp
  in decimal seconds, any number of decimals.
* **SVIn2's pose-graph trajectory** (its `#timestamp tx ty tz qx qy qz qw`
  file): the same columns, but the stamp is written as the whole seconds, a
  '.', and then the nanoseconds as a plain integer *without zero padding*, so
  `1731151716.65535333` is 1731151716 s + 65 535 333 ns (0.0655 s, not
  0.655 s). Read as a decimal such a file jumps back and forth in time.
* **Named-column CSV** as OKVIS (and SVIn2's VIO front end, which is OKVIS)
  write it: a header line `timestamp, p_WS_W_x, p_WS_W_y, p_WS_W_z, q_WS_x,
  q_WS_y, q_WS_z, q_WS_w, v_WS_W_x, ..., b_a_z` and integer nanosecond
  stamps; or SVIn2's keyframe list `#ID, timestamp, qx, qy, qz, qw, tx, ty,
  tz`. Columns are found by their header names (`tx`/`x`, `qx`, or
  `p_<AB>_<A>_x`, `q_<AB>_x`, EuRoC's `[unit]` suffixes allowed); the others
  (ids, velocities, biases) are ignored, and so are fields past the named
  ones (OKVIS appends each camera's extrinsics to a row without naming them).

**Stamps.** Every stamp becomes int64 nanoseconds by integer arithmetic on
its digits (never through a float). `format="tum"` reads `S.F` as decimal
seconds; `format="svin"` reads it as S seconds plus F nanoseconds (F at most
9 digits; with exactly 9 digits both readings agree). In a named-column file
whose position columns are `p_<AB>_...` (the OKVIS/EuRoC convention) a stamp
without a '.' is integer nanoseconds, as those tools write it; elsewhere it is
whole seconds.

**`format="auto"`, decided once per file** from the fractional parts F of
its `S.F` stamps and these facts about writers: a fixed-precision decimal
writer (`%.6f`, `std::fixed`) gives every F the same length; a shortest-form
decimal writer (repr, `%g`, default iostreams) never ends F with a '0'; an
unpadded-nanosecond writer never starts F with a '0' (unless F is 9 digits
or just "0"), but may end it with one. In order:

1. a stamp with a sign, an exponent or more than 9 decimals: decimal seconds;
2. every F of the same length (all 9 digits included, where both readings
   agree): decimal seconds;
3. an F of 2-8 digits starting with '0': decimal seconds (an unpadded
   integer has no leading zero);
4. an F of 2 or more digits ending in '0': SVIn2 nanoseconds (a shortest-form
   decimal has no trailing zero, and fixed precision was ruled out by 2);
5. otherwise the reading under which the stamps strictly increase, when
   exactly one does;
6. otherwise the file cannot tell: InputError asking for `format`.

Rules 3 and 4 contradicting each other is case 6 too. The one case decided
wrongly is an SVIn2 file whose every nanosecond count has the same number of
digits below 9 (every stamp within 0.01-0.1 s past its second, say): rule 2
reads it as decimals. Pass `format="svin"` for such a file.

**Odd records.** A line that is not a pose (wrong number of fields, not
numbers, non-finite, zero quaternion) is skipped with a warning naming the
first such line; so is a pose whose stamp is not after the previous one,
unless more than one and more than 1 % of the poses are (then the stamps are
being misread, and InputError says so). Quaternions are normalised.

**Frames.** `pose_frame` is what the header says the poses are of: `body`
for `p_WS`/`p_WB`/`p_RS` columns, `camera` for `p_WC`; None when the file
does not say (TUM columns, SVIn2's files). S is the sensor the file is of:
the IMU (our body frame) in OKVIS's output and in EuRoC's
`state_groundtruth_estimate0`, but the Vicon marker in EuRoC's `vicon0`.
"""

from __future__ import annotations

import itertools
import logging
import math
import re
from dataclasses import dataclass
from decimal import InvalidOperation
from pathlib import Path
from typing import Literal

import numpy as np

from shared.clock import NS_PER_S
from shared.errors import InputError
from shared.formats.tum import parse_stamp_ns
from shared.geometry import make_pose, matrix_from_quat_xyzw
from shared.trajectory import Trajectory

log = logging.getLogger(__name__)

TrajectoryFormat = Literal["auto", "tum", "svin"]
StampReading = Literal["tum", "svin", "ns"]
PoseFrame = Literal["body", "camera"]
FORMATS: tuple[TrajectoryFormat, ...] = ("auto", "tum", "svin")

_TUM_COLUMNS = ("timestamp", "tx", "ty", "tz", "qx", "qy", "qz", "qw")
_PLAIN_STAMP = re.compile(r"^(\d+)(?:\.(\d*))?$")
_FIELD_SPLIT = re.compile(r"[,\s]+")
# p_WS_W_x (OKVIS: S in W, expressed in W), p_RS_R_x [m] (EuRoC), q_WS_x / q_RS_w.
_FRAME_POSITION = re.compile(r"^p_([A-Za-z])([A-Za-z])_[A-Za-z]_([xyz])$")
_FRAME_ROTATION = re.compile(r"^q_([A-Za-z])([A-Za-z])_([xyzw])$")
_BODY_LETTERS = {"S", "B", "I"}
_CAMERA_LETTERS = {"C"}
_STAMP_NAMES = {"timestamp", "time", "t", "stamp", "timestamp_ns", "timestamp_s"}
_MAX_DISORDER = 0.01


@dataclass(frozen=True, kw_only=True)
class TrajectoryText:
    """A trajectory read from text, with how it was read.

    `stamps`: how the stamps were read ("tum": decimal seconds, "svin":
    seconds + unpadded nanoseconds, "ns": integer nanoseconds); `layout`:
    "tum" (the 8 TUM columns, no header naming others) or "named" (columns
    found by header name); `pose_frame`: "body", "camera" or None (the file
    does not say); `reason`: why this stamp reading (the rule of the module
    docstring, or "given"); `warnings`: skipped lines, one string each kind.
    """

    trajectory: Trajectory
    stamps: StampReading
    layout: Literal["tum", "named"]
    pose_frame: PoseFrame | None
    reason: str
    warnings: tuple[str, ...] = ()


@dataclass(frozen=True)
class _Columns:
    """Indices of the stamp, position (x, y, z) and quaternion (x, y, z, w) columns."""

    count: int | None  # fields a data line must have (None: exactly 8, TUM)
    stamp: int
    position: tuple[int, int, int]
    quat_xyzw: tuple[int, int, int, int]
    pose_frame: PoseFrame | None
    integer_ns: bool  # a stamp without '.' is nanoseconds (OKVIS / EuRoC convention)


_TUM = _Columns(None, 0, (1, 2, 3), (4, 5, 6, 7), None, False)


def _header_columns(text: str) -> _Columns | None:
    """The columns a header line names, or None when it is not such a header."""
    body = text.lstrip("#").strip()
    if not body:
        return None
    parts = body.split(",") if "," in body else body.split()
    names = [re.sub(r"\[.*?\]", "", part).strip() for part in parts]
    stamp = None
    pos: dict[str, int] = {}
    quat: dict[str, int] = {}
    frame: PoseFrame | None = None
    integer_ns = False
    for index, name in enumerate(names):
        low = name.lower()
        if low in _STAMP_NAMES and stamp is None:
            stamp = index
            integer_ns = integer_ns or low.endswith("_ns") or "[ns]" in parts[index]
        elif low in ("tx", "ty", "tz", "x", "y", "z"):
            pos.setdefault(low[-1], index)
        elif low in ("qx", "qy", "qz", "qw"):
            quat.setdefault(low[-1], index)
        elif match := _FRAME_POSITION.match(name):
            pos.setdefault(match.group(3), index)
            frame = frame or _frame_of(match.group(2))
            integer_ns = True
        elif match := _FRAME_ROTATION.match(name):
            quat.setdefault(match.group(3), index)
            frame = frame or _frame_of(match.group(2))
    if stamp is None or set(pos) != {"x", "y", "z"} or set(quat) != {"x", "y", "z", "w"}:
        return None
    columns = _Columns(
        len(names),
        stamp,
        (pos["x"], pos["y"], pos["z"]),
        (quat["x"], quat["y"], quat["z"], quat["w"]),
        frame,
        integer_ns,
    )
    tum_order = (stamp, columns.position, columns.quat_xyzw) == (
        _TUM.stamp,
        _TUM.position,
        _TUM.quat_xyzw,
    )
    if tum_order and len(names) == 8 and frame is None and not integer_ns:
        return _TUM  # the TUM header itself: its columns, nothing more
    return columns


def _frame_of(letter: str) -> PoseFrame | None:
    if letter.upper() in _BODY_LETTERS:
        return "body"
    if letter.upper() in _CAMERA_LETTERS:
        return "camera"
    return None


def parse_svin_stamp_ns(text: str) -> int:
    """SVIn2's `S.F` (F the nanoseconds, unpadded, at most 9 digits) to int ns.

    `S` alone is whole seconds. Raises ValueError for anything else.
    """
    match = _PLAIN_STAMP.match(text)
    if match is None:
        raise ValueError(f"timestamp {text!r} is not seconds.nanoseconds")
    whole, frac = match.group(1), match.group(2) or "0"
    if len(frac) > 9:
        raise ValueError(f"timestamp {text!r} has more than 9 nanosecond digits")
    stamp_ns = int(whole) * NS_PER_S + int(frac)
    if stamp_ns >= 2**63:
        raise ValueError(f"timestamp {text!r} beyond the int64 nanosecond range")
    return stamp_ns


def _parse_integer_ns(text: str) -> int:
    if not text.isdigit():
        raise ValueError(f"timestamp {text!r} is not integer nanoseconds")
    stamp_ns = int(text)
    if stamp_ns >= 2**63:
        raise ValueError(f"timestamp {text!r} beyond the int64 nanosecond range")
    return stamp_ns


def choose_stamp_reading(stamps: list[str]) -> tuple[StampReading, str] | None:
    """Rules 1-5 of the module docstring for one file's stamp texts: (reading, reason),
    or None when the stamps cannot tell (rule 6)."""
    fracs: list[str] = []
    numbers: list[str] = []
    for text in stamps:
        match = _PLAIN_STAMP.match(text)
        if match is None:
            try:
                parse_stamp_ns(text)
            except (ValueError, InvalidOperation):
                continue  # not a number at all: an odd line, skipped when read
            return "tum", f"stamp {text!r} has a sign or an exponent: decimal seconds"
        numbers.append(text)
        frac = match.group(2)
        if frac is not None and len(frac) > 9:
            return "tum", f"stamp {text!r} has more than 9 decimals: decimal seconds"
        fracs.append(frac or "")
    if len({len(f) for f in fracs}) <= 1:
        return "tum", "every stamp has as many decimals: decimal seconds"
    leading = next((f for f in fracs if 2 <= len(f) <= 8 and f[0] == "0"), None)
    trailing = next((f for f in fracs if len(f) >= 2 and f[-1] == "0"), None)
    if leading is not None and trailing is None:
        return "tum", f"fraction {leading!r} starts with 0 (not unpadded nanoseconds): decimal"
    if trailing is not None and leading is None:
        return "svin", (
            f"fractions of varying length, {trailing!r} ending in 0 "
            "(not a shortest decimal): seconds + unpadded nanoseconds"
        )
    if leading is None:  # neither rule 3 nor 4: order decides (rule 5)
        increasing = {}
        for reading, parse in (("tum", parse_stamp_ns), ("svin", parse_svin_stamp_ns)):
            try:
                values = [parse(text) for text in numbers]
            except (ValueError, InvalidOperation):
                increasing[reading] = False
                continue
            increasing[reading] = all(b > a for a, b in itertools.pairwise(values))
        if increasing["tum"] and not increasing["svin"]:
            return "tum", "stamps increase only when read as decimal seconds"
        if increasing["svin"] and not increasing["tum"]:
            return "svin", "stamps increase only when read as seconds + unpadded nanoseconds"
    return None


def read_trajectory(path: Path | str, *, format: TrajectoryFormat = "auto") -> TrajectoryText:
    """Read a TUM, SVIn2 or OKVIS trajectory file (see the module docstring for the rules).

    `format`: "tum" (decimal-second stamps), "svin" (SVIn2's seconds +
    unpadded nanoseconds) or "auto" (decided from the stamps). Raises
    InputError naming the file for an unreadable file, a file with no poses,
    stamps that cannot be told apart (auto) or that go backwards too often
    for the reading chosen, and an unknown `format`.
    """
    path = Path(path)
    if format not in FORMATS:
        raise InputError(
            f"{path.name}: unknown trajectory format {format!r} (expected one of "
            f"{', '.join(FORMATS)})"
        )
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path.name}: cannot read trajectory ({exc})") from exc
    columns = _TUM
    rows: list[tuple[int, list[str]]] = []
    odd: list[tuple[int, str]] = []  # (line number, why) of lines that are not poses
    for line_no, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line:
            continue
        if line.startswith("#") or (not rows and not _looks_numeric(line)):
            named = _header_columns(line)
            if named is not None and not rows:
                columns = named
            elif not line.startswith("#"):
                odd.append((line_no, f"not a pose or a header ({line[:60]!r})"))
            continue
        fields = [f for f in _FIELD_SPLIT.split(line) if f]
        if columns.count is None and len(fields) != 8:
            odd.append((line_no, f"expected 8 fields, found {len(fields)}"))
            continue
        # Named columns: more fields than named are fine (OKVIS appends camera extrinsics,
        # 7 numbers per camera, that its header does not name).
        if columns.count is not None and len(fields) < columns.count:
            odd.append((line_no, f"expected {columns.count} fields, found {len(fields)}"))
            continue
        rows.append((line_no, fields))
    stamp_texts = [fields[columns.stamp] for _, fields in rows]
    reading, reason = _reading(path, format, columns, stamp_texts)

    stamps: list[int] = []
    values: list[list[float]] = []
    line_nos: list[int] = []
    for line_no, fields in rows:
        try:
            stamp_ns = _parse(reading, fields[columns.stamp])
            numbers = [float(fields[i]) for i in (*columns.position, *columns.quat_xyzw)]
        except (ValueError, InvalidOperation) as exc:
            odd.append((line_no, f"not a pose ({exc})"))
            continue
        if not all(math.isfinite(v) for v in numbers):
            odd.append((line_no, "non-finite value"))
            continue
        if math.hypot(*numbers[3:]) < 1e-6:
            odd.append((line_no, "zero quaternion"))
            continue
        # Divided by its largest component first: squaring 1e200 would overflow the norm.
        largest = max(abs(v) for v in numbers[3:])
        numbers[3:] = [v / largest for v in numbers[3:]]
        stamps.append(stamp_ns)
        values.append(numbers)
        line_nos.append(line_no)
    warnings: list[str] = []
    if odd:
        first_no, why = min(odd)
        warnings.append(f"{len(odd)} line(s) skipped (first: {path.name}:{first_no}: {why})")
    if not stamps:
        raise InputError(
            f"{path.name}: no poses (expected lines '{' '.join(_TUM_COLUMNS)}' or an "
            f"OKVIS/SVIn2 header naming the columns)" + (f"; {warnings[0]}" if warnings else "")
        )
    keep = _in_order(stamps)
    disordered = len(stamps) - int(sum(keep))
    if disordered:
        first = line_nos[keep.index(False)]
        if disordered > max(1.0, _MAX_DISORDER * len(stamps)):
            hint = {
                "tum": "; if the file is SVIn2's (nanoseconds not zero-padded), read it with "
                "format='svin' (--trajectory-format svin)",
                "svin": "; if its stamps are decimal seconds (TUM), read it with format='tum' "
                "(--trajectory-format tum)",
                "ns": "",
            }[reading]
            raise InputError(
                f"{path.name}:{first}: {disordered} of {len(stamps)} time stamps are not after "
                f"the previous line's when read as {_READING_NAMES[reading]} (expected "
                f"strictly increasing stamps){hint}"
            )
        warnings.append(
            f"{disordered} pose(s) with a stamp not after the previous one skipped "
            f"(first: {path.name}:{first})"
        )
        stamps = [s for s, k in zip(stamps, keep, strict=True) if k]
        values = [v for v, k in zip(values, keep, strict=True) if k]
    for warning in warnings:
        log.warning("%s: %s", path.name, warning)
    data = np.asarray(values, dtype=np.float64)
    poses = make_pose(matrix_from_quat_xyzw(data[:, 3:7]), data[:, 0:3])
    return TrajectoryText(
        trajectory=Trajectory(np.asarray(stamps, dtype=np.int64), poses),
        stamps=reading,
        layout="tum" if columns.count is None else "named",
        pose_frame=columns.pose_frame,
        reason=reason,
        warnings=tuple(warnings),
    )


_READING_NAMES = {
    "tum": "decimal seconds",
    "svin": "seconds + unpadded nanoseconds",
    "ns": "integer nanoseconds",
}


def _looks_numeric(line: str) -> bool:
    first = _FIELD_SPLIT.split(line, maxsplit=1)[0]
    try:
        float(first)
    except ValueError:
        return False
    return True


def _reading(
    path: Path, format: TrajectoryFormat, columns: _Columns, stamps: list[str]
) -> tuple[StampReading, str]:
    if columns.integer_ns and stamps and all(s.isdigit() for s in stamps):
        return "ns", "integer stamps under OKVIS/EuRoC column names: nanoseconds"
    chosen = choose_stamp_reading(stamps)
    if format != "auto":
        if chosen is not None and chosen[0] != format:
            log.warning(
                "%s: stamps read as %s as asked; the file looks otherwise: %s",
                path.name,
                _READING_NAMES[format],
                chosen[1],
            )
        return format, "given"
    if chosen is None:
        raise InputError(
            f"{path.name}: cannot tell whether the stamps are decimal seconds (TUM) or "
            f"seconds + unpadded nanoseconds (SVIn2): both readings fit; give "
            f"format='tum' or 'svin' (--trajectory-format tum|svin)"
        )
    return chosen


def _parse(reading: StampReading, text: str) -> int:
    if reading == "svin":
        return parse_svin_stamp_ns(text)
    if reading == "ns":
        return _parse_integer_ns(text)
    return parse_stamp_ns(text)


def _in_order(stamps: list[int]) -> list[bool]:
    """Keep flags: a stamp not after the last kept one is dropped."""
    keep: list[bool] = []
    last: int | None = None
    for stamp in stamps:
        ok = last is None or stamp > last
        keep.append(ok)
        if ok:
            last = stamp
    return keep


__all__ = [
    "FORMATS",
    "PoseFrame",
    "StampReading",
    "TrajectoryFormat",
    "TrajectoryText",
    "choose_stamp_reading",
    "parse_svin_stamp_ns",
    "read_trajectory",
]
