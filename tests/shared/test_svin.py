"""SVIn2 / OKVIS / TUM trajectory text: stamps read exactly, the file kind told apart."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from shared.errors import InputError
from shared.formats.svin import choose_stamp_reading, parse_svin_stamp_ns, read_trajectory
from shared.formats.tum import parse_stamp_ns, read_tum, write_tum
from shared.geometry import make_pose, quat_xyzw_from_matrix, so3_exp
from shared.trajectory import Trajectory

# SVIn2's pose-graph trajectory: whole seconds, '.', the nanoseconds as a plain integer.
SVIN_HEADER = "#timestamp tx ty tz qx qy qz qw"
OKVIS_HEADER = (
    "timestamp, p_WS_W_x, p_WS_W_y, p_WS_W_z, q_WS_x, q_WS_y, q_WS_z, q_WS_w, "
    "v_WS_W_x, v_WS_W_y, v_WS_W_z, b_g_x, b_g_y, b_g_z, b_a_x, b_a_y, b_a_z"
)


def _trajectory(stamps_ns: list[int], seed: int = 0) -> Trajectory:
    rng = np.random.default_rng(seed)
    n = len(stamps_ns)
    poses = make_pose(so3_exp(rng.normal(size=(n, 3))), rng.normal(scale=5.0, size=(n, 3)))
    return Trajectory(np.asarray(stamps_ns, dtype=np.int64), poses)


def _svin_text(trajectory: Trajectory) -> str:
    """What SVIn2's pose graph writes: fixed 9-decimal numbers, unpadded nanoseconds."""
    quats = quat_xyzw_from_matrix(trajectory.rotations)
    lines = [SVIN_HEADER]
    for k, stamp in enumerate(trajectory.stamps_ns.tolist()):
        sec, nsec = divmod(stamp, 10**9)
        numbers = " ".join(f"{v:.9f}" for v in (*trajectory.positions[k], *quats[k]))
        lines.append(f"{sec}.{nsec} {numbers}")
    return "\n".join(lines) + "\n"


# Keyframes a few per second; some nanosecond counts have fewer than 9 digits and would
# sort wrongly as decimals (x.65535333 is 0.0655 s, before x.1 s).
STAMPS_NS = [
    1_731_151_716_065_535_333,
    1_731_151_716_210_000_000,
    1_731_151_716_733_120_004,
    1_731_151_717_004_500_000,
    1_731_151_717_350_200_100,
    1_731_151_717_999_999_999,
    1_731_151_718_000_000_007,
    1_731_151_718_512_000_000,
]


def test_svin_stamps_are_read_exactly(tmp_path: Path) -> None:
    truth = _trajectory(STAMPS_NS)
    path = tmp_path / "svin.txt"
    path.write_text(_svin_text(truth))
    assert "1731151716.65535333 " in path.read_text()  # the spelling of the issue
    for fmt in ("auto", "svin"):
        read = read_trajectory(path, format=fmt)
        np.testing.assert_array_equal(read.trajectory.stamps_ns, STAMPS_NS)
        np.testing.assert_allclose(read.trajectory.poses, truth.poses, atol=1e-8)
        assert read.stamps == "svin" and read.layout == "tum" and read.pose_frame is None
        assert read.warnings == ()
    assert "ending in 0" in read_trajectory(path).reason
    # The strict TUM reader, and this one told "tum", refuse it and say what to do.
    with pytest.raises(InputError, match=r"svin\.txt:3: timestamp .* SVIn2"):
        read_tum(path)
    with pytest.raises(InputError, match=r"svin\.txt:\d+: .*--trajectory-format svin"):
        read_trajectory(path, format="tum")


def test_parse_svin_stamp() -> None:
    assert parse_svin_stamp_ns("1731151716.65535333") == 1_731_151_716_065_535_333
    assert parse_svin_stamp_ns("1731151716.7") == 1_731_151_716_000_000_007
    assert parse_svin_stamp_ns("1731151716.065535333") == 1_731_151_716_065_535_333
    assert parse_svin_stamp_ns("12") == 12 * 10**9
    for bad in ("1.0000000001", "-1.5", "1e9", "1.2.3", ""):
        with pytest.raises(ValueError):
            parse_svin_stamp_ns(bad)


def test_tum_files_still_read_as_decimal_seconds(tmp_path: Path) -> None:
    truth = _trajectory(STAMPS_NS)
    ours = write_tum(tmp_path / "ours.tum", truth)  # 9 decimals: both readings agree
    read = read_trajectory(ours)
    np.testing.assert_array_equal(read.trajectory.stamps_ns, STAMPS_NS)
    assert read.stamps == "tum" and read.reason.startswith("every stamp has as many")
    # Fixed 6 decimals (evo, ORB-SLAM's TUM output), and shortest floats (Python repr).
    fixed = tmp_path / "fixed.txt"
    micro = [s for s in STAMPS_NS if s % 10**9 > 1000]  # distinct at 6 decimals
    fixed.write_text(
        "".join(f"{s // 10**9}.{s % 10**9 // 1000:06d} 0 0 0 0 0 0 1\n" for s in micro)
    )
    np.testing.assert_array_equal(
        read_trajectory(fixed).trajectory.stamps_ns, np.array(micro) // 1000 * 1000
    )
    shortest = tmp_path / "repr.txt"
    stamps_s = [1731151716.0655, 1731151716.5, 1731151717.25, 1731151717.3, 1731151718.125]
    shortest.write_text("".join(f"{s!r} 1 2 3 0 0 0 1\n" for s in stamps_s))
    read = read_trajectory(shortest)
    assert read.stamps == "tum" and "starts with 0" in read.reason
    np.testing.assert_array_equal(read.trajectory.stamps_ns, read_tum(shortest).stamps_ns)


def test_order_decides_when_digits_do_not(tmp_path: Path) -> None:
    # No leading or trailing zeros; only one reading increases.
    svin = ["100.5", "100.25", "101.7", "101.333"]  # 5, 25 ns ... increasing only as svin
    assert choose_stamp_reading(svin) == (
        "svin",
        "stamps increase only when read as seconds + unpadded nanoseconds",
    )
    tum = ["100.25", "100.5", "101.333", "101.7"]
    assert choose_stamp_reading(tum) == ("tum", "stamps increase only when read as decimal seconds")
    both = ["100.5", "101.25", "102.7"]
    assert choose_stamp_reading(both) is None
    path = tmp_path / "both.txt"
    path.write_text("".join(f"{s} 0 0 0 0 0 0 1\n" for s in both))
    with pytest.raises(InputError, match=r"both\.txt: cannot tell .*--trajectory-format"):
        read_trajectory(path)
    assert read_trajectory(path, format="svin").trajectory.stamps_ns[1] == 101 * 10**9 + 25
    assert read_trajectory(path, format="tum").trajectory.stamps_ns[1] == 101_250_000_000
    assert choose_stamp_reading(["100.05", "100.10", "101.5"]) is None  # 3 and 4 both apply


def test_okvis_csv_gives_body_poses_with_integer_ns(tmp_path: Path) -> None:
    truth = _trajectory(STAMPS_NS, seed=3)
    quats = quat_xyzw_from_matrix(truth.rotations)
    lines = [OKVIS_HEADER]
    for k, stamp in enumerate(STAMPS_NS):
        sec, nsec = divmod(stamp, 10**9)
        # Velocity, biases, then one camera's extrinsics, which the header does not name.
        extra = [0.1, -0.2, 0.3, 1e-4, 2e-4, -3e-4, 0.01, 0.02, -0.03, 0.0, 0.1, 0.0, 0, 0, 0, 1]
        numbers = ", ".join(f"{v:.18e}" for v in (*truth.positions[k], *quats[k], *extra))
        lines.append(f"{sec}{nsec:09d}, {numbers}")
    path = tmp_path / "okvis.csv"
    path.write_text("\n".join(lines) + "\n")
    read = read_trajectory(path)
    np.testing.assert_array_equal(read.trajectory.stamps_ns, STAMPS_NS)
    np.testing.assert_allclose(read.trajectory.poses, truth.poses, atol=1e-12)
    assert (read.stamps, read.layout, read.pose_frame) == ("ns", "named", "body")


def test_svin_keyframe_list_and_euroc_columns(tmp_path: Path) -> None:
    truth = _trajectory(STAMPS_NS[:3], seed=4)
    quats = quat_xyzw_from_matrix(truth.rotations)
    rows = ["#ID, timestamp, qx, qy, qz, qw, tx, ty, tz"]
    for k, stamp in enumerate(STAMPS_NS[:3]):
        sec, nsec = divmod(stamp, 10**9)
        q, t = quats[k], truth.positions[k]
        rows.append(f"{k}, {sec}.{nsec:09d}, " + ", ".join(f"{v:.9f}" for v in (*q, *t)))
    path = tmp_path / "keyframes.csv"
    path.write_text("\n".join(rows) + "\n")
    read = read_trajectory(path)
    np.testing.assert_array_equal(read.trajectory.stamps_ns, STAMPS_NS[:3])
    np.testing.assert_allclose(read.trajectory.poses, truth.poses, atol=1e-8)
    assert read.layout == "named" and read.pose_frame is None
    # EuRoC ground truth: w first, units in brackets, ns stamps; RS = sensor in reference.
    euroc = tmp_path / "data.csv"
    euroc.write_text(
        "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], "
        "q_RS_y [], q_RS_z []\n"
        "1403715273262142976,0.878,2.142,0.948,0.0,0.0,0.0,1.0\n"
        "1403715273267142912,0.879,2.143,0.949,0.0,0.0,1.0,0.0\n"
    )
    read = read_trajectory(euroc)
    assert read.trajectory.stamps_ns.tolist() == [1403715273262142976, 1403715273267142912]
    # (w, x, y, z) = (0, 0, 0, 1): a half turn about z, not the identity of x, y, z, w order.
    np.testing.assert_allclose(read.trajectory.rotations[0], np.diag([-1.0, -1.0, 1.0]))
    np.testing.assert_allclose(read.trajectory.rotations[1], np.diag([-1.0, 1.0, -1.0]))
    assert read.pose_frame == "body"


def test_odd_lines_are_skipped_with_a_warning(tmp_path: Path, caplog) -> None:
    text = _svin_text(_trajectory(STAMPS_NS)).splitlines()
    text.insert(3, "1731151716.5 1 2 3")  # too few fields
    text.insert(5, "1731151716.9 1 2 3 0 0 0 0")  # zero quaternion
    path = tmp_path / "odd.txt"
    path.write_text("\n".join(text) + "\n")
    read = read_trajectory(path)
    np.testing.assert_array_equal(read.trajectory.stamps_ns, STAMPS_NS)
    assert read.warnings == ("2 line(s) skipped (first: odd.txt:4: expected 8 fields, found 4)",)
    assert "2 line(s) skipped" in caplog.text
    # One repeated pose is skipped; many out-of-order stamps mean a wrong reading.
    lines = _svin_text(_trajectory(STAMPS_NS)).splitlines()
    path.write_text("\n".join([*lines[:4], lines[3], *lines[4:]]) + "\n")
    read = read_trajectory(path, format="svin")
    assert len(read.trajectory) == len(STAMPS_NS)
    assert "1 pose(s) with a stamp not after the previous one skipped" in read.warnings[0]


def test_files_without_poses_are_refused(tmp_path: Path) -> None:
    path = tmp_path / "none.txt"
    path.write_text("# nothing here\n\nnot a header\n1 2 3\n")
    with pytest.raises(InputError, match=r"none\.txt: no poses .*2 line\(s\) skipped"):
        read_trajectory(path)
    with pytest.raises(InputError, match=r"missing\.txt: cannot read"):
        read_trajectory(tmp_path / "missing.txt")
    with pytest.raises(InputError, match=r"unknown trajectory format 'orb'"):
        read_trajectory(path, format="orb")  # type: ignore[arg-type]


# Never a wrong answer: a file from either writer is read exactly or refused as ambiguous.
_stamp_lists = st.lists(st.integers(min_value=1, max_value=3 * 10**9), min_size=2, max_size=40).map(
    lambda steps: (1_700_000_000 * 10**9 + np.cumsum(steps)).tolist()
)


def _read_as(reading: str, texts: list[str]) -> list[int]:
    parse = parse_svin_stamp_ns if reading == "svin" else parse_stamp_ns
    return [parse(t) for t in texts]


@settings(max_examples=200, deadline=None)
@given(_stamp_lists)
def test_unpadded_nanoseconds_are_never_misread(stamps_ns: list[int]) -> None:
    texts = [f"{s // 10**9}.{s % 10**9}" for s in stamps_ns]
    lengths = {len(t.split(".")[1]) for t in texts}
    assume(lengths == {9} or len(lengths) > 1)  # the documented blind spot: one length below 9
    chosen = choose_stamp_reading(texts)
    if chosen is not None:
        assert _read_as(chosen[0], texts) == stamps_ns, chosen


@settings(max_examples=200, deadline=None)
@given(_stamp_lists)
def test_shortest_decimals_are_never_misread(stamps_ns: list[int]) -> None:
    texts = []
    for s in stamps_ns:
        frac = f"{s % 10**9:09d}".rstrip("0") or "0"
        texts.append(f"{s // 10**9}.{frac}")
    chosen = choose_stamp_reading(texts)
    if chosen is not None:
        assert _read_as(chosen[0], texts) == stamps_ns, chosen
