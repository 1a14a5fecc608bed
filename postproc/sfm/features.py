"""SIFT extraction and matching of chosen pairs, with bounded budgets (pycolmap, CPU).

Run time of the whole stage is decided here: extraction costs about 0.3-0.5 s
per full-size image and matching 20-160 ms per pair, so the image size, the
feature count and the pair list are all capped. Only the pairs written to the
pairs file are matched (`pycolmap.match_image_pairs` with an imported pair
list) and each is verified geometrically (two-view geometry by RANSAC).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from shared.fsutil import write_text_atomic


@dataclass(kw_only=True)
class FeatureOptions:
    """Budgets of the feature stage.

    max_num_features: SIFT keypoints kept per image (largest scales first).
    max_image_size_px: longer image side for extraction (images are scaled down, the
        keypoints scaled back to full resolution).
    max_ratio: Lowe's ratio test threshold. max_error_px: RANSAC threshold of the
        two-view verification (pixels). min_num_inliers: verified pairs need this many.
    first_octave: first octave of the SIFT pyramid. COLMAP's -1 doubles the image first,
        which costs about 3/4 of the extraction time and adds the finest features, the
        first to go when `max_num_features` caps the count (largest scales are kept);
        None: -1 for small images (longer side below `small_image_px`), else 0.
    num_threads: worker threads (-1: all cores).
    """

    max_num_features: int = 1024
    max_image_size_px: int = 1280
    max_ratio: float = 0.8
    max_error_px: float = 4.0
    min_num_inliers: int = 15
    first_octave: int | None = None
    small_image_px: int = 480
    num_threads: int = -1

    def __post_init__(self) -> None:
        if self.max_num_features < 64:
            raise ValueError(f"max_num_features must be at least 64, got {self.max_num_features}")
        if self.max_image_size_px < 64:
            raise ValueError(f"max_image_size_px must be at least 64, got {self.max_image_size_px}")
        if not 0 < self.max_ratio <= 1:
            raise ValueError(f"max_ratio must be in (0, 1], got {self.max_ratio}")


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

    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = int(options.max_image_size_px)
    extraction.num_threads = int(options.num_threads)
    extraction.sift.max_num_features = int(options.max_num_features)
    extraction.sift.first_octave = first_octave(options, longest_side_px)
    pycolmap.extract_features(
        database_path,
        image_dir,
        image_names=list(image_names),
        extraction_options=extraction,
        device=pycolmap.Device.cpu,
    )


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
