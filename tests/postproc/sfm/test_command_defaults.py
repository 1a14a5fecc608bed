"""The sfm command's flags come from the stage's options: their help states the
stage's own defaults, and no flag given leaves the stage's defaults."""

from __future__ import annotations

import re

import pytest

from postproc.cli import COMMAND_MODULES, DESCRIPTION
from postproc.pipeline.options import options_from_args
from postproc.sfm.features import FeatureOptions
from postproc.sfm.pairs import PairOptions
from postproc.sfm.stage import SfmOptions
from shared.cli import build_parser
from shared.errors import InputError


def _sfm_parser():
    parser = build_parser("wreckmap-post", DESCRIPTION, COMMAND_MODULES)
    sub = next(a for a in parser._actions if a.dest == "command")
    assert isinstance(sub.choices, dict)
    sfm = sub.choices["sfm"]
    sfm.format_help()  # the stage's flags are added on first use
    return parser, sfm


def test_sfm_help_defaults_match_the_stage() -> None:
    _, sfm = _sfm_parser()
    helps = {a.option_strings[0]: a.help or "" for a in sfm._actions if a.option_strings}
    expected = {
        "--max-features": FeatureOptions().max_num_features,
        "--max-image-size": FeatureOptions().max_image_size_px,
        "--sequential": PairOptions().sequential_neighbours,
        "--spatial": PairOptions().spatial_neighbours,
        "--spatial-radius": PairOptions().spatial_radius_m,
    }
    for flag, value in expected.items():
        stated = re.search(r"default: ([0-9.]+)", helps[flag])
        assert stated is not None, flag
        assert float(stated.group(1)) == float(value), flag


def test_sfm_flags_build_the_stage_options() -> None:
    from postproc.commands.sfm import SFM_FLAGS

    parser, _ = _sfm_parser()
    args = parser.parse_args(["sfm", "in", "--out", "out"])
    assert options_from_args(SfmOptions, args, SFM_FLAGS) == SfmOptions()
    args = parser.parse_args(
        ["sfm", "in", "--out", "out", "--max-features", "256", "--spatial-radius", "2.5",
         "--mapper", "incremental", "--refine-intrinsics", "--threads", "2",
         "--prior-sigma", "0.2"]
    )  # fmt: skip
    options = options_from_args(SfmOptions, args, SFM_FLAGS)
    assert options.features.max_num_features == 256
    assert options.pairs.spatial_radius_m == 2.5
    assert options.refine.mapper == "incremental" and options.refine.refine_intrinsics
    assert options.features.num_threads == options.refine.num_threads == 2
    assert options.prior_sigma_m == 0.2
    # The options' own checks run: a value they refuse is one line naming it.
    args = parser.parse_args(["sfm", "in", "--out", "out", "--max-features", "10"])
    with pytest.raises(InputError, match="max_num_features must be at least 64"):
        options_from_args(SfmOptions, args, SFM_FLAGS)
