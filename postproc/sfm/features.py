"""SIFT extraction and matching of chosen pairs, with bounded budgets (pycolmap, CPU).

Run time of the whole stage is decided here: extraction costs about 0.3-0.5 s
per full-size image and matching 20-160 ms per pair, so the image size, the
feature count and the pair list are all capped. Only the pairs written to the
pairs file are matched (`pycolmap.match_image_pairs` with an imported pair
list) and each is verified geometrically (two-view geometry by RANSAC).

Both steps can be spread over workers (`extract_features_mapped`,
`match_pairs_mapped`): a `MapFn` runs top-level task functions on chunks that
hold paths and options only; each task writes one `.npz` result file atomically
(features of its images, or matches and two-view geometries of its pairs) and the
stage imports them into its one database, which only it writes.
"""

from __future__ import annotations

import hashlib
import shutil
import tempfile
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from postproc.sfm.options import FeatureOptions as FeatureOptions
from shared.errors import StageError
from shared.fsutil import atomic_path, write_text_atomic
from shared.progress import MapFn

#: A map over workers: `map_fn(function, items)` returns `[function(item) for item in
#: items]` in order, where `function` is a picklable top-level function and the items
#: hold paths and options only (a process pool's or a Dask client's map, for example).


def first_octave(options: FeatureOptions, longest_side_px: int) -> int:
    """The SIFT first octave for images whose longer side is `longest_side_px` (pixels)."""
    if options.first_octave is not None:
        return int(options.first_octave)
    size = min(longest_side_px, options.max_image_size_px)
    return -1 if size < options.small_image_px else 0


def extract_features(
    database_path: Path,
    image_dir: Path,
    image_names: Sequence[str],
    options: FeatureOptions,
    *,
    longest_side_px: int,
) -> None:
    """SIFT keypoints and descriptors of `image_names` (relative to `image_dir`) into the DB.

    longest_side_px: the longer side of the images (pixels), to choose the first octave.

    The images must already be in the database (with their cameras): COLMAP then
    keeps their cameras and frames and only adds features; images that already
    have features are skipped (a resumed run redoes nothing).
    """
    import pycolmap

    pycolmap.extract_features(
        database_path,
        image_dir,
        image_names=list(image_names),
        extraction_options=_extraction_options(options, longest_side_px),
        device=pycolmap.Device.cpu,
    )


def _extraction_options(options: FeatureOptions, longest_side_px: int) -> Any:
    import pycolmap

    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = int(options.max_image_size_px)
    extraction.num_threads = int(options.num_threads)
    extraction.sift.max_num_features = int(options.max_num_features)
    extraction.sift.first_octave = first_octave(options, longest_side_px)
    return extraction


@dataclass(frozen=True, kw_only=True)
class ExtractionChunk:
    """One worker's share of the extraction (paths and options only, picklable).

    image_dir: the run's image folder; names: image names relative to it;
    longest_side_px: the longer image side (pixels, chooses the first octave);
    features_path: the `.npz` file the worker writes (atomically).
    """

    image_dir: str
    names: tuple[str, ...]
    options: FeatureOptions
    longest_side_px: int
    features_path: str


def extract_chunk(chunk: ExtractionChunk) -> str:
    """Worker: SIFT of the chunk's images into `chunk.features_path`; returns that path.

    Top-level and picklable for process pools and Dask. Extracts into a private
    scratch database beside the output, then stores per image `keypoints_<k>`
    (float32, COLMAP's 6-column affine keypoints in full-resolution pixels) and
    `descriptors_<k>` (uint8) with the image names in `names`. A file already there
    is kept (a resumed run redoes nothing).
    """
    import pycolmap

    final = Path(chunk.features_path)
    if final.exists():
        return str(final)
    final.parent.mkdir(parents=True, exist_ok=True)
    arrays: dict[str, Any] = {"names": np.asarray(chunk.names, dtype=str)}
    with tempfile.TemporaryDirectory(prefix=f".{final.stem}.", dir=final.parent) as scratch:
        database = Path(scratch) / "chunk.db"
        pycolmap.extract_features(
            database,
            chunk.image_dir,
            image_names=list(chunk.names),
            extraction_options=_extraction_options(chunk.options, chunk.longest_side_px),
            device=pycolmap.Device.cpu,
        )
        with pycolmap.Database.open(database) as db:
            ids = {image.name: int(image.image_id) for image in db.read_all_images()}
            for k, name in enumerate(chunk.names):
                image_id = ids.get(name)
                if image_id is None or not db.exists_keypoints(image_id):
                    raise StageError(
                        f"{Path(chunk.image_dir) / name}: no features extracted (expected a "
                        "readable image)"
                    )
                arrays[f"keypoints_{k}"] = np.asarray(db.read_keypoints(image_id), np.float32)
                arrays[f"descriptors_{k}"] = np.asarray(
                    db.read_descriptors(image_id).data, np.uint8
                )
    with atomic_path(final, overwrite=True) as tmp, tmp.open("wb") as f:
        np.savez(f, **arrays)
    return str(final)


def import_features(database_path: Path, features_path: Path) -> int:
    """Write the features of one chunk file into the database; returns images written.

    Images that already have keypoints in the database are left as they are.
    """
    import pycolmap

    try:
        data = np.load(features_path)
    except (OSError, ValueError) as error:
        raise StageError(
            f"{features_path}: unreadable features file ({error}; expected the .npz of "
            "extract_chunk)"
        ) from error
    written = 0
    with data, pycolmap.Database.open(database_path) as db:
        for k, name in enumerate(data["names"].tolist()):
            image = db.read_image_with_name(name)
            if image is None:
                raise StageError(
                    f"{features_path}: image {name} is not in {database_path} (features "
                    "from another run?)"
                )
            if db.exists_keypoints(image.image_id):
                continue
            db.write_keypoints(image.image_id, data[f"keypoints_{k}"])
            db.write_descriptors(
                image.image_id,
                pycolmap.FeatureDescriptors(
                    pycolmap.FeatureExtractorType.SIFT, data[f"descriptors_{k}"]
                ),
            )
            written += 1
    return written


def extract_features_mapped(
    database_path: Path,
    image_dir: Path,
    image_names: Sequence[str],
    options: FeatureOptions,
    *,
    longest_side_px: int,
    features_dir: Path,
    map_fn: MapFn,
    chunk_size: int,
) -> None:
    """`extract_features` spread over `map_fn` in chunks of `chunk_size` images.

    Each chunk becomes `features_dir/chunk_NNNNN.npz` (see `extract_chunk`), then the
    files are imported into the one database in chunk order. Images with features
    already in the database are not sent out again.
    """
    import pycolmap

    with pycolmap.Database.open(database_path) as db:
        todo = []
        for name in image_names:
            image = db.read_image_with_name(name)
            if image is None or not db.exists_keypoints(image.image_id):
                todo.append(name)
    if not todo:
        return
    chunks = []
    for start in range(0, len(todo), chunk_size):
        names = tuple(todo[start : start + chunk_size])
        chunks.append(
            ExtractionChunk(
                image_dir=str(image_dir),
                names=names,
                options=options,
                longest_side_px=int(longest_side_px),
                features_path=str(
                    features_dir / f"{_chunk_key((names, longest_side_px), options)}.npz"
                ),
            )
        )
    paths = map_fn(extract_chunk, chunks)
    _check_results(paths, chunks, "extraction")
    for path in paths:
        import_features(database_path, Path(path))
    shutil.rmtree(features_dir, ignore_errors=True)


def _chunk_key(content: object, options: FeatureOptions) -> str:
    """A file name for a chunk's result: a resumed run reuses a file only when the chunk
    holds the same images (or pairs) under the same options."""
    text = repr((content, sorted(asdict(options).items())))
    return hashlib.sha1(text.encode()).hexdigest()[:16]


def _check_results(paths: list[Any], chunks: list[Any], step: str) -> None:
    if len(paths) != len(chunks):
        raise StageError(
            f"map_fn returned {len(paths)} results for {len(chunks)} {step} chunks "
            "(expected one per chunk, in order)"
        )


@dataclass(frozen=True, kw_only=True)
class MatchingChunk:
    """One worker's share of the matching (paths and options only, picklable).

    database_path: the run's database holding every image's features (only read);
    pairs: image-name pairs to match and verify; matches_path: the `.npz` file the
    worker writes (atomically).
    """

    database_path: str
    pairs: tuple[tuple[str, str], ...]
    options: FeatureOptions
    matches_path: str


_NAN33 = np.full((3, 3), np.nan)


def match_chunk(chunk: MatchingChunk) -> str:
    """Worker: match and verify the chunk's pairs into `chunk.matches_path`; returns it.

    Top-level and picklable. Matches on a private copy of the database (SQLite is
    not written by two processes) and stores per pair `matches_<k>` (uint32, (M, 2)
    feature indices), `inliers_<k>` (the verified subset), `config_<k>` (COLMAP's
    two-view configuration) and `F_<k>`, `E_<k>`, `H_<k>` (NaN when not estimated),
    with the pairs in `pairs`. A file already there is kept.
    """
    import pycolmap

    final = Path(chunk.matches_path)
    if final.exists():
        return str(final)
    final.parent.mkdir(parents=True, exist_ok=True)
    arrays: dict[str, Any] = {"pairs": np.asarray(chunk.pairs, dtype=str).reshape(-1, 2)}
    with tempfile.TemporaryDirectory(prefix=f".{final.stem}.", dir=final.parent) as scratch:
        database = Path(scratch) / "chunk.db"
        shutil.copyfile(chunk.database_path, database)
        with pycolmap.Database.open(database) as db:
            db.clear_matches()
            db.clear_two_view_geometries()
            ids = {image.name: int(image.image_id) for image in db.read_all_images()}
        for a, b in chunk.pairs:
            if a not in ids or b not in ids:
                raise StageError(
                    f"{chunk.database_path}: pair {a} {b} names an image that is not in the "
                    "database (expected the run's image names)"
                )
        pairs_path = write_pairs_file(Path(scratch) / "pairs.txt", chunk.pairs)
        match_pairs(database, pairs_path, chunk.options)
        with pycolmap.Database.open(database) as db:
            for k, (a, b) in enumerate(chunk.pairs):
                id_a, id_b = ids[a], ids[b]
                arrays[f"matches_{k}"] = np.asarray(db.read_matches(id_a, id_b), np.uint32)
                geometry = db.read_two_view_geometry(id_a, id_b)
                arrays[f"inliers_{k}"] = np.asarray(geometry.inlier_matches, np.uint32)
                arrays[f"config_{k}"] = np.int64(int(geometry.config))
                for key in ("F", "E", "H"):
                    value = getattr(geometry, key)
                    arrays[f"{key}_{k}"] = _NAN33 if value is None else np.asarray(value)
    with atomic_path(final, overwrite=True) as tmp, tmp.open("wb") as f:
        np.savez(f, **arrays)
    return str(final)


def import_matches(database_path: Path, matches_path: Path) -> int:
    """Write the matches and two-view geometries of one chunk file; returns pairs written.

    Pairs already verified in the database are left as they are.
    """
    import pycolmap

    try:
        data = np.load(matches_path)
    except (OSError, ValueError) as error:
        raise StageError(
            f"{matches_path}: unreadable matches file ({error}; expected the .npz of match_chunk)"
        ) from error
    written = 0
    with data, pycolmap.Database.open(database_path) as db:
        ids = {image.name: int(image.image_id) for image in db.read_all_images()}
        for k, (a, b) in enumerate(data["pairs"].tolist()):
            if a not in ids or b not in ids:
                raise StageError(
                    f"{matches_path}: pair {a} {b} is not in {database_path} (matches from "
                    "another run?)"
                )
            if db.exists_two_view_geometry(ids[a], ids[b]):
                continue
            if not db.exists_matches(ids[a], ids[b]):
                db.write_matches(ids[a], ids[b], data[f"matches_{k}"])
            geometry = pycolmap.TwoViewGeometry()
            geometry.config = pycolmap.TwoViewGeometryConfiguration(int(data[f"config_{k}"]))
            geometry.inlier_matches = data[f"inliers_{k}"]
            for key in ("F", "E", "H"):
                value = data[f"{key}_{k}"]
                if not np.isnan(value).any():
                    setattr(geometry, key, value)
            db.write_two_view_geometry(ids[a], ids[b], geometry)
            written += 1
    return written


def match_pairs_mapped(
    database_path: Path,
    pairs: Sequence[tuple[str, str]],
    options: FeatureOptions,
    *,
    matches_dir: Path,
    map_fn: MapFn,
    chunk_size: int,
) -> None:
    """`match_pairs` spread over `map_fn` in chunks of `chunk_size` pairs.

    Each chunk becomes `matches_dir/<hash>.npz` (see `match_chunk`), imported into the
    one database in order. Pairs already verified in the database are not sent out.
    """
    import pycolmap

    with pycolmap.Database.open(database_path) as db:
        ids = {image.name: int(image.image_id) for image in db.read_all_images()}
        todo = [
            (a, b)
            for a, b in pairs
            if a in ids and b in ids and not db.exists_two_view_geometry(ids[a], ids[b])
        ]
    if not todo:
        return
    chunks = []
    for start in range(0, len(todo), chunk_size):
        part = tuple(todo[start : start + chunk_size])
        chunks.append(
            MatchingChunk(
                database_path=str(database_path),
                pairs=part,
                options=options,
                matches_path=str(matches_dir / f"{_chunk_key(part, options)}.npz"),
            )
        )
    paths = map_fn(match_chunk, chunks)
    _check_results(paths, chunks, "matching")
    for path in paths:
        import_matches(database_path, Path(path))
    shutil.rmtree(matches_dir, ignore_errors=True)


def write_pairs_file(path: Path, pairs: Sequence[tuple[str, str]]) -> Path:
    """COLMAP's imported pair list: one "name1 name2" line per pair."""
    return write_text_atomic(path, "".join(f"{a} {b}\n" for a, b in pairs), overwrite=True)


def match_pairs(database_path: Path, pairs_path: Path, options: FeatureOptions) -> None:
    """Match and verify exactly the pairs of `pairs_path` (pairs already matched are skipped)."""
    import pycolmap

    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = int(options.num_threads)
    matching.sift.max_ratio = float(options.max_ratio)
    pairing = pycolmap.ImportedPairingOptions()
    pairing.match_list_path = pairs_path
    verification = pycolmap.TwoViewGeometryOptions()
    verification.min_num_inliers = int(options.min_num_inliers)
    verification.ransac.max_error = float(options.max_error_px)
    pycolmap.match_image_pairs(
        database_path,
        matching_options=matching,
        pairing_options=pairing,
        verification_options=verification,
        device=pycolmap.Device.cpu,
    )


def match_statistics(database_path: Path) -> dict[str, int]:
    """Matched pairs, verified pairs (with inliers), raw matches and inlier matches in the DB."""
    import pycolmap

    with pycolmap.Database.open(database_path) as db:
        _, inliers = db.read_two_view_geometry_num_inliers()
        return {
            "matched_pairs": int(db.num_matched_image_pairs()),
            "verified_pairs": int(sum(1 for n in inliers if n > 0)),
            "matches": int(db.num_matches()),
            "inlier_matches": int(db.num_inlier_matches()),
            "keypoints": int(db.num_keypoints()),
        }
