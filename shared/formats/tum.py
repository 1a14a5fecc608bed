"""TUM trajectory text files: `timestamp tx ty tz qx qy qz qw`, one pose a line.

The format of the TUM RGB-D benchmark (Sturm et al. 2012), read by evo and
most SLAM evaluation tools: the timestamp in seconds since the epoch, the
translation in metres, the rotation as a unit quaternion in x, y, z, w order.
Lines starting with '#' are comments; fields are separated by whitespace (or
commas, which some tools write).

Stamps are converted between decimal seconds and int64 nanoseconds with
integer arithmetic on the digits, so nanosecond stamps survive a write/read
round trip exactly (a float64 only holds epoch seconds to ~0.24 µs).
"""

from __future__ import annotations

import math
from decimal import ROUND_HALF_EVEN, Decimal, InvalidOperation
from pathlib import Path

import numpy as np

from shared.clock import NS_PER_S
from shared.errors import InputError
from shared.fsutil import write_text_atomic
from shared.geometry import make_pose, matrix_from_quat_xyzw, quat_xyzw_from_matrix
from shared.trajectory import Trajectory

_FIELDS = "timestamp tx ty tz qx qy qz qw"
_MAX_STAMP_S = Decimal(2**63) / NS_PER_S


def parse_stamp_ns(text: str) -> int:
    """Decimal seconds (any precision, exponent allowed) to int ns, rounded half to even.

    Raises ValueError (or decimal.InvalidOperation for text that is not a number).
    """
    value = Decimal(text)  # exact decimal of the digits, no float on the way
    if not value.is_finite():
        raise ValueError(f"non-finite timestamp {text!r}")
    # Checked before scaling: "1e999999999" would overflow the decimal context, and
    # anything beyond int64 nanoseconds (year 2262) cannot be stored.
    # (adjusted() is the decimal exponent, read without the context that abs() would apply.)
    if value.adjusted() > 12 or value.copy_abs() > _MAX_STAMP_S:
        raise ValueError(f"timestamp {text!r} beyond the int64 nanosecond range")
    stamp_ns = int((value * NS_PER_S).quantize(Decimal(1), rounding=ROUND_HALF_EVEN))
    if not -(2**63) <= stamp_ns < 2**63:
        raise ValueError(f"timestamp {text!r} beyond the int64 nanosecond range")
    return stamp_ns


def format_stamp_ns(stamp_ns: int) -> str:
    """Int ns to decimal seconds with exactly 9 decimals ("1700000000.000000001")."""
    sign = "-" if stamp_ns < 0 else ""
    whole, frac = divmod(abs(int(stamp_ns)), NS_PER_S)
    return f"{sign}{whole}.{frac:09d}"


def read_tum(path: Path | str) -> Trajectory:
    """Read a TUM trajectory; stamps become int64 ns, quaternions rotation matrices.

    Quaternions are normalised on reading (files often keep few digits).
    Raises InputError naming the file and line for a line without 8 numbers, a
    zero or non-finite quaternion, a time stamp not after the previous one, an
    unreadable file, or a file with no poses.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path.name}: cannot read TUM trajectory ({exc})") from exc
    stamps: list[int] = []
    rows: list[list[float]] = []
    for line_no, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        fields = line.replace(",", " ").split()
        where = f"{path.name}:{line_no}"
        if len(fields) != 8:
            raise InputError(f"{where}: expected 8 numbers ({_FIELDS}), found {len(fields)}")
        try:
            stamp_ns = parse_stamp_ns(fields[0])
            values = [float(f) for f in fields[1:]]
        except (ValueError, InvalidOperation) as exc:
            raise InputError(f"{where}: expected 8 numbers ({_FIELDS}), found {line!r}") from exc
        if not all(math.isfinite(v) for v in values):
            raise InputError(f"{where}: non-finite value in {line!r}")
        if math.hypot(*values[3:]) < 1e-6:
            raise InputError(f"{where}: zero quaternion (expected a unit quaternion qx qy qz qw)")
        # Divided by its largest component first: squaring 1e200 would overflow the norm.
        largest = max(abs(v) for v in values[3:])
        values[3:] = [v / largest for v in values[3:]]
        if stamps and stamp_ns <= stamps[-1]:
            raise InputError(
                f"{where}: timestamp {fields[0]} is not after the previous line's "
                f"(expected strictly increasing time stamps; an SVIn2 file, whose "
                f"nanoseconds are not zero-padded, is read by shared.formats.svin)"
            )
        stamps.append(stamp_ns)
        rows.append(values)
    if not rows:
        raise InputError(f"{path.name}: no poses (expected lines '{_FIELDS}')")
    data = np.asarray(rows, dtype=np.float64)
    poses = make_pose(matrix_from_quat_xyzw(data[:, 3:7]), data[:, 0:3])
    return Trajectory(np.asarray(stamps, dtype=np.int64), poses)


def format_tum(trajectory: Trajectory) -> str:
    """The TUM text of a trajectory (header comment plus one line per pose)."""
    quats = quat_xyzw_from_matrix(trajectory.rotations)
    positions = trajectory.positions
    lines = [f"# {_FIELDS}"]
    for k, stamp in enumerate(trajectory.stamps_ns.tolist()):
        # repr of a float is the shortest string that reads back to the same float.
        numbers = " ".join(repr(float(v)) for v in (*positions[k], *quats[k]))
        lines.append(f"{format_stamp_ns(stamp)} {numbers}")
    return "\n".join(lines) + "\n"


def write_tum(path: Path | str, trajectory: Trajectory, *, overwrite: bool = False) -> Path:
    """Write a trajectory as TUM text, atomically; returns the path.

    Stamps are written with 9 decimals from the integer nanoseconds (exact);
    translations and quaternions with the shortest exact float text. Raises
    OutputExistsError if `path` exists and `overwrite` is false.
    """
    return write_text_atomic(path, format_tum(trajectory), overwrite=overwrite)
