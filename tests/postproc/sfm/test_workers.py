"""The SfM stage with its per-image work spread over worker processes (`map_fn`)."""

from __future__ import annotations

import json
import multiprocessing
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap
import pytest

from postproc.sfm.features import (
    ExtractionChunk,
    FeatureOptions,
    MatchingChunk,
    extract_chunk,
    import_features,
    import_matches,
)
from postproc.sfm.stage import SfmOptions, run
from shared.errors import StageError
from shared.formats.tum import read_tum
from sim.slam_like import SlamLikeSession, write_merge_like

MapFn = Callable[[Callable[[Any], Any], list[Any]], list[Any]]


def options() -> SfmOptions:
    # Small chunks so that several tasks of each kind go to the two workers.
    features = FeatureOptions(max_num_features=512, num_threads=1)
    sfm = SfmOptions(features=features, chunk_images=16, chunk_pairs=60)
    sfm.refine.num_threads = 2
    # The workers do the per-image work (extraction, matching): one refinement pass is
    # enough to compare the models (the rebuild pass is tested in test_refine.py).
    sfm.refine.rebuild_tracks = False
    return sfm


@pytest.fixture(scope="module")
def pool_map() -> Iterator[MapFn]:
    # Spawned workers: forking a process that holds pycolmap's threads is unsafe.
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(2, mp_context=context) as pool:

        def map_fn(function: Callable[[Any], Any], items: list[Any]) -> list[Any]:
            return list(pool.map(function, items))

        yield map_fn


def keypoint_counts(database: Path) -> dict[str, int]:
    with pycolmap.Database.open(database) as db:
        return {
            image.name: int(db.num_keypoints_for_image(image.image_id))
            for image in db.read_all_images()
        }


@pytest.fixture(scope="module")
def runs(
    slam_survey: list[SlamLikeSession], pool_map: MapFn, tmp_path_factory: pytest.TempPathFactory
) -> tuple[Path, Path, list[int]]:
    """The stage on one merge folder run locally and over two worker processes."""
    root = tmp_path_factory.mktemp("sfm_workers")
    merge = write_merge_like(root / "merge", slam_survey, placed=[True, True])
    local = run(options(), [merge], root / "local")
    calls: list[int] = []

    def counting_map(function: Callable[[Any], Any], items: list[Any]) -> list[Any]:
        calls.append(len(items))
        return pool_map(function, items)

    mapped = run(options(), [merge], root / "mapped", map_fn=counting_map)
    return local, mapped, calls


@pytest.mark.slow
def test_process_pool_gives_the_local_result(
    slam_survey: list[SlamLikeSession], runs: tuple[Path, Path, list[int]]
) -> None:
    local, mapped, calls = runs
    n = sum(len(s.estimate) for s in slam_survey)
    assert calls[0] == -(-n // 16)  # extraction chunks
    assert len(calls) == 2 and calls[1] >= 2  # matching chunks
    # Same features, image by image (SIFT on the CPU is deterministic).
    assert keypoint_counts(local.parents[1] / "database.db") == keypoint_counts(
        mapped.parents[1] / "database.db"
    )
    stats = [json.loads((p.parents[1] / "stats.json").read_text()) for p in (local, mapped)]
    assert stats[0]["matches"]["matched_pairs"] == stats[1]["matches"]["matched_pairs"]
    # Verified inliers differ a little: COLMAP's RANSAC is seeded at random.
    inliers = [s["matches"]["inlier_matches"] for s in stats]
    assert abs(inliers[0] - inliers[1]) < 0.05 * inliers[0]
    models = [pycolmap.Reconstruction(p) for p in (local, mapped)]
    names = [{im.name for im in m.images.values() if im.has_pose} for m in models]
    assert names[0] == names[1] and len(names[0]) >= 0.9 * n
    for session in slam_survey:
        a, b = (
            read_tum(p.parents[1] / "sessions" / session.folder.name / "keyframes.tum")
            for p in (local, mapped)
        )
        np.testing.assert_array_equal(a.stamps_ns, b.stamps_ns)
        assert np.max(np.linalg.norm(a.poses[:, :3, 3] - b.poses[:, :3, 3], axis=1)) < 0.02
    # The workers' scratch files are gone once imported.
    assert not (mapped.parents[1] / "features_chunks").exists()
    assert not (mapped.parents[1] / "matches_chunks").exists()


def test_map_fn_returning_too_few_results_is_a_stage_error(
    slam_survey: list[SlamLikeSession], tmp_path: Path
) -> None:
    def lossy(function: Callable[[Any], Any], items: list[Any]) -> list[Any]:
        return [function(item) for item in items[:-1]]

    with pytest.raises(StageError, match=r"results for \d+ extraction chunks"):
        run(options(), [slam_survey[0].folder], tmp_path / "out", map_fn=lossy)


def test_chunk_files_are_checked_on_import(
    slam_survey: list[SlamLikeSession], tmp_path: Path
) -> None:
    image_dir = slam_survey[0].folder / "keyframes"
    name = sorted(p.name for p in image_dir.iterdir())[0]
    chunk = ExtractionChunk(
        image_dir=str(image_dir),
        names=(name,),
        options=FeatureOptions(max_num_features=128, num_threads=1),
        longest_side_px=320,
        features_path=str(tmp_path / "chunk.npz"),
    )
    path = Path(extract_chunk(chunk))
    assert extract_chunk(chunk) == str(path)  # an existing file is kept
    with np.load(path) as data:
        assert data["keypoints_0"].shape[1] == 6 and data["descriptors_0"].shape[1] == 128
    database = tmp_path / "other.db"
    pycolmap.Database.open(database).close()
    with pytest.raises(StageError, match="is not in"):
        import_features(database, path)
    (tmp_path / "broken.npz").write_bytes(b"not a zip")
    with pytest.raises(StageError, match="unreadable features file"):
        import_features(database, tmp_path / "broken.npz")
    with pytest.raises(StageError, match="unreadable matches file"):
        import_matches(database, tmp_path / "broken.npz")
    missing = ExtractionChunk(
        image_dir=str(image_dir),
        names=("no_such_image.png",),
        options=chunk.options,
        longest_side_px=320,
        features_path=str(tmp_path / "missing.npz"),
    )
    with pytest.raises(StageError, match="no features extracted"):
        extract_chunk(missing)
    assert not (tmp_path / "missing.npz").exists()


@pytest.mark.slow
def test_matches_of_another_run_are_refused(
    slam_survey: list[SlamLikeSession], runs: tuple[Path, Path, list[int]], tmp_path: Path
) -> None:
    from postproc.sfm.features import match_chunk

    out = runs[0].parents[1]
    prefix = slam_survey[0].folder.name
    first, second = sorted(p.name for p in (out / "images" / prefix).iterdir())[:2]
    path = match_chunk(
        MatchingChunk(
            database_path=str(out / "database.db"),
            pairs=((f"{prefix}/{first}", f"{prefix}/{second}"),),
            options=options().features,
            matches_path=str(tmp_path / "m.npz"),
        )
    )
    with np.load(path) as data:
        assert data["matches_0"].shape[1] == 2 and len(data["inliers_0"]) > 15
    ghost = MatchingChunk(
        database_path=str(out / "database.db"),
        pairs=((f"{prefix}/{first}", "ghost.png"),),
        options=options().features,
        matches_path=str(tmp_path / "ghost.npz"),
    )
    with pytest.raises(StageError, match="names an image that is not in the database"):
        match_chunk(ghost)
    assert not (tmp_path / "ghost.npz").exists()
    database = tmp_path / "other.db"
    pycolmap.Database.open(database).close()
    with pytest.raises(StageError, match="is not in"):
        import_matches(database, Path(path))


@pytest.mark.parametrize("kwargs", [{"chunk_images": 0}, {"chunk_pairs": 0}])
def test_empty_chunks_are_refused(kwargs: dict[str, Any]) -> None:
    with pytest.raises(ValueError, match="chunk_images and chunk_pairs must be at least 1"):
        SfmOptions(**kwargs)
