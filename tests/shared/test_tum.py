"""TUM trajectory files: exact round trips, clear errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from shared.errors import InputError, OutputExistsError
from shared.formats.tum import format_stamp_ns, read_tum, write_tum
from shared.geometry import make_pose, matrix_from_quat_xyzw, so3_exp
from shared.trajectory import Trajectory


def random_trajectory(n: int, seed: int) -> Trajectory:
    rng = np.random.default_rng(seed)
    # Stamps with arbitrary nanoseconds, near the present epoch.
    stamps = 1_700_000_000_000_000_000 + np.cumsum(rng.integers(1, 10**9, size=n))
    poses = make_pose(
        so3_exp(rng.normal(scale=2.0, size=(n, 3))), rng.normal(scale=50.0, size=(n, 3))
    )
    return Trajectory(stamps.astype(np.int64), poses)


@pytest.mark.parametrize("seed", range(3))
def test_round_trip_exact(tmp_path: Path, seed: int) -> None:
    traj = random_trajectory(200, seed)
    path = write_tum(tmp_path / "traj.tum", traj)
    assert path == tmp_path / "traj.tum"
    back = read_tum(path)
    np.testing.assert_array_equal(back.stamps_ns, traj.stamps_ns)
    np.testing.assert_allclose(back.poses, traj.poses, atol=1e-9, rtol=0)
    # Writing what was read gives the same stamps and numbers (to quaternion round-off).
    again = write_tum(tmp_path / "again.tum", back)
    rows_a = [line.split() for line in path.read_text().splitlines()[1:]]
    rows_b = [line.split() for line in again.read_text().splitlines()[1:]]
    assert [r[0] for r in rows_a] == [r[0] for r in rows_b]
    numbers_a = np.array([[float(v) for v in r[1:]] for r in rows_a])
    numbers_b = np.array([[float(v) for v in r[1:]] for r in rows_b])
    np.testing.assert_allclose(numbers_b, numbers_a, atol=1e-13, rtol=0)


def test_stamp_format() -> None:
    assert format_stamp_ns(1_700_000_000_000_000_001) == "1700000000.000000001"
    assert format_stamp_ns(0) == "0.000000000"
    assert format_stamp_ns(-1_500_000_000) == "-1.500000000"


def test_written_text_is_tum(tmp_path: Path) -> None:
    traj = Trajectory(
        np.array([1_403_636_579_763_555_584], dtype=np.int64),
        make_pose(np.diag([-1.0, -1.0, 1.0]), [1.0, -2.5, 0.0])[None],  # half turn about z
    )
    text = write_tum(tmp_path / "t.tum", traj).read_text()
    lines = text.splitlines()
    assert lines[0].startswith("#")
    fields = lines[1].split()
    assert fields[0] == "1403636579.763555584"
    np.testing.assert_allclose([float(f) for f in fields[1:]], [1.0, -2.5, 0.0, 0.0, 0.0, 1.0, 0.0])
    # Any TUM reader (numpy here) gets the same numbers.
    loaded = np.loadtxt(tmp_path / "t.tum", ndmin=2)
    assert loaded.shape == (1, 8)


def test_read_foreign_file(tmp_path: Path) -> None:
    path = tmp_path / "groundtruth.txt"
    path.write_text(
        "# ground truth trajectory\n"
        "# timestamp tx ty tz qx qy qz qw\n"
        "\n"
        "1305031102.175304 1.3405 0.6266 1.6575 0.6574 0.6126 -0.2949 -0.3248\n"
        "1305031102.2 1.3303,0.6256,1.6464,0.6579,0.6161,-0.2932,-0.3189\n"
        "1.3050311023e9 1 2 3 0 0 0 2\n"
    )
    traj = read_tum(path)
    np.testing.assert_array_equal(
        traj.stamps_ns,
        [1_305_031_102_175_304_000, 1_305_031_102_200_000_000, 1_305_031_102_300_000_000],
    )
    q = np.array([0.6574, 0.6126, -0.2949, -0.3248])
    np.testing.assert_allclose(traj.rotations[0], matrix_from_quat_xyzw(q / np.linalg.norm(q)))
    np.testing.assert_allclose(traj.rotations[2], np.eye(3))  # non-unit quaternion normalised
    np.testing.assert_allclose(traj.positions[1], [1.3303, 0.6256, 1.6464])


@pytest.mark.parametrize(
    ("line", "message"),
    [
        (
            "1.0 2.0 3.0 4.0 5.0",
            r"traj\.tum:3: expected 8 numbers \(timestamp tx ty tz qx qy qz qw\), found 5",
        ),
        ("1.0 2.0 3.0 4.0 0 0 0 1 9", r"traj\.tum:3: expected 8 numbers .*found 9"),
        ("1.0 x 3.0 4.0 0 0 0 1", r"traj\.tum:3: expected 8 numbers"),
        ("abc 2.0 3.0 4.0 0 0 0 1", r"traj\.tum:3: expected 8 numbers"),
        ("nan 2.0 3.0 4.0 0 0 0 1", r"traj\.tum:3: expected 8 numbers"),
        ("3.0 2.0 inf 4.0 0 0 0 1", r"traj\.tum:3: non-finite"),
        ("3.0 2.0 3.0 4.0 0 0 0 0", r"traj\.tum:3: zero quaternion"),
        ("0.5 2.0 3.0 4.0 0 0 0 1", r"traj\.tum:3: timestamp 0.5 is not after"),
        ("1.0 2.0 3.0 4.0 0 0 0 1", r"traj\.tum:3: timestamp 1.0 is not after"),
    ],
)
def test_bad_lines(tmp_path: Path, line: str, message: str) -> None:
    path = tmp_path / "traj.tum"
    path.write_text(f"# header\n1.0 0 0 0 0 0 0 1\n{line}\n")
    with pytest.raises(InputError, match=message):
        read_tum(path)


def test_unreadable_and_empty(tmp_path: Path) -> None:
    with pytest.raises(InputError, match=r"missing\.tum: cannot read"):
        read_tum(tmp_path / "missing.tum")
    (tmp_path / "empty.tum").write_text("# only a comment\n\n")
    with pytest.raises(InputError, match=r"empty\.tum: no poses"):
        read_tum(tmp_path / "empty.tum")
    (tmp_path / "binary.tum").write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(InputError, match=r"binary\.tum: cannot read"):
        read_tum(tmp_path / "binary.tum")


def test_write_refuses_to_overwrite(tmp_path: Path) -> None:
    first = random_trajectory(5, 10)
    second = random_trajectory(7, 11)
    path = write_tum(tmp_path / "out.tum", first)
    with pytest.raises(OutputExistsError, match=r"out\.tum"):
        write_tum(path, second)
    assert len(read_tum(path)) == 5
    write_tum(path, second, overwrite=True)
    assert len(read_tum(path)) == 7
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.tum"]
