"""The sfm command's help states the stage's own defaults (the CLI passes none of its own)."""

from __future__ import annotations

import re

from postproc.cli import COMMAND_MODULES, DESCRIPTION
from postproc.sfm.features import FeatureOptions
from postproc.sfm.pairs import PairOptions
from shared.cli import build_parser


def test_sfm_help_defaults_match_the_stage() -> None:
    parser = build_parser("wreckmap-post", DESCRIPTION, COMMAND_MODULES)
    sub = next(a for a in parser._actions if a.dest == "command")
    sfm = sub.choices["sfm"]
    helps = {a.dest: a.help or "" for a in sfm._actions}
    expected = {
        "max_features": FeatureOptions().max_num_features,
        "max_image_size": FeatureOptions().max_image_size_px,
        "sequential": PairOptions().sequential_neighbours,
        "spatial": PairOptions().spatial_neighbours,
        "spatial_radius": PairOptions().spatial_radius_m,
    }
    for dest, value in expected.items():
        stated = re.search(r"default ([0-9.]+)", helps[dest])
        assert stated is not None, dest
        assert float(stated.group(1)) == float(value), dest
    args = parser.parse_args(["sfm", "in", "--out", "out"])
    assert args.max_features is None and args.sequential is None
