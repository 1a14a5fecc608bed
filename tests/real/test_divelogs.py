"""Real dive logs through `wreckmap-field dc import`, and Subsurface's own test corpus.

Two sets of real files:

* every file in ../shared/data/divelogs, imported through the command line with
  the dive counts and maximum depths expected (test42.uddf against Subsurface's own
  reading of it, test-42-uddf-import-reference.xml);
* the XML, SSRF and UDDF test files of Subsurface's `dives/` folder copied to
  tests/data/subsurface-dives (its README says which and from where): each one
  imports, with the dives and depths Subsurface itself reads where the repository
  holds its reading, or is refused with one line naming why.
"""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from field.divecomputer.importers import import_logbook, read_logbook
from shared.errors import InputError
from shared.formats.diveprofile import DiveProfile, read_dive_folder

REPO = Path(__file__).resolve().parents[2]
SHARED_DATA = REPO.parent / "shared" / "data"
DIVELOGS = SHARED_DATA / "divelogs"
CORPUS = REPO / "tests" / "data" / "subsurface-dives"

pytestmark = pytest.mark.timeout(120)


def subsurface_reading(path: Path) -> list[tuple[int, float, float]]:
    """Per divecomputer with samples in a Subsurface-written file: (samples, deepest
    sample in m, the maximum depth Subsurface recorded in m), read with plain
    ElementTree, independently of our importer. Subsurface writes metres ('12.3 m')."""
    root = ET.parse(path).getroot()  # our own reference files: no entities
    found = []
    for dive in root.iter("dive"):
        for computer in dive.findall("divecomputer") or [dive]:
            depths = [float(s.get("depth", "nan").split()[0]) for s in computer.findall("sample")]
            if not depths:
                continue
            summary = computer.find("depth")
            recorded = math.nan if summary is None else float(summary.get("max", "nan").split()[0])
            found.append((len(depths), float(np.nanmax(depths)), recorded))
    return found


def run_import(path: Path, out: Path) -> subprocess.CompletedProcess[str]:
    command = [sys.executable, "-m", "field.cli", "dc", "import", str(path), "--out", str(out)]
    return subprocess.run(command, cwd=REPO, capture_output=True, text=True, timeout=60)


# ---------------------------------------------------------- ../shared/data/divelogs

# file: maximum depth of each dive's samples in m, in start order (the dive count is
# the length). test42.uddf is checked against Subsurface's reading instead.
SHARED_EXPECTED = {
    "ostc.xml": [26.097, 26.998],
    "shearwater-perdix2-dive68.uddf": [12.5914631],
    "shearwater-petrel3-dive88.csv": [53.6],
    "test-42-uddf-import-reference.xml": [38.97],
}


def test_every_shared_divelog_is_covered() -> None:
    names = {p.name for p in DIVELOGS.iterdir()}
    assert names == set(SHARED_EXPECTED) | {"test42.uddf"}


@pytest.mark.parametrize("name", sorted(SHARED_EXPECTED))
def test_shared_divelog_through_the_cli(tmp_path: Path, name: str) -> None:
    out = tmp_path / "dives"
    done = run_import(DIVELOGS / name, out)
    assert done.returncode == 0, done.stderr
    index = json.loads((out / "dives.json").read_text())["dives"]
    assert [entry["max_depth_m"] for entry in index] == pytest.approx(SHARED_EXPECTED[name])
    assert done.stdout.split() == [str(out / entry["csv"]) for entry in index]
    # A second import adds nothing and changes nothing.
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    again = run_import(DIVELOGS / name, out)
    assert again.returncode == 0 and again.stdout == ""
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_test42_uddf_matches_subsurface_reading(tmp_path: Path) -> None:
    reference = DIVELOGS / "test-42-uddf-import-reference.xml"
    out = tmp_path / "dives"
    done = run_import(DIVELOGS / "test42.uddf", out)
    assert done.returncode == 0, done.stderr
    ours = read_dive_folder(out)
    theirs = subsurface_reading(reference)
    assert len(ours) == len(theirs) == 1
    (samples, deepest, recorded), dive = theirs[0], ours[0]
    assert dive.stamps_s.size == samples and dive.max_depth_m == deepest
    assert dive.max_depth_m <= recorded  # Subsurface keeps the UDDF greatestdepth, 38.99 m
    (reference_dive,) = read_logbook(reference)
    np.testing.assert_array_equal(dive.stamps_s, reference_dive.stamps_s)
    np.testing.assert_array_equal(dive.depth_m, reference_dive.depth_m)


def test_a_refused_import_leaves_the_folder_as_it_was(tmp_path: Path) -> None:
    out = tmp_path / "dives"
    assert run_import(DIVELOGS / "ostc.xml", out).returncode == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    # The same logbook with every date removed: no dive can be placed in time.
    undated = tmp_path / "undated.xml"
    text = (DIVELOGS / "ostc.xml").read_text()
    undated.write_text(re.sub(r" date='[^']*'", "", text))
    done = run_import(undated, out)
    assert done.returncode == 1
    assert done.stderr.count("\n") == 1 + done.stderr.count("WARNING")  # one error line
    assert re.search(
        r"undated\.xml: no importable dive \(dive 1 divecomputer 1: no date; 1 more dive",
        done.stderr,
    )
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


# ------------------------------------------------------ Subsurface's dives/ corpus

IMPORTS = "imports"
REFUSED = "refused"
NO_SAMPLES = (
    r"no importable dive \(dive (?:\d+|#\d+ \(number \d+\))(?: divecomputer 1)?: no samples"
)

# file: (IMPORTS, [(start, samples, deepest sample m), ...]) or (REFUSED, reason regex).
# Numbers are the files' own (sample elements counted with grep); files Subsurface wrote
# are also checked against their recorded summary below.
CORPUS_EXPECTED: dict[str, tuple[str, object]] = {
    "test1.xml": (REFUSED, NO_SAMPLES),
    "test2.xml": (REFUSED, NO_SAMPLES),
    "test3.xml": (REFUSED, NO_SAMPLES),
    "test4.xml": (REFUSED, NO_SAMPLES),
    "test5.xml": (REFUSED, NO_SAMPLES),
    "test6.xml": (REFUSED, NO_SAMPLES),
    "test7.xml": (REFUSED, NO_SAMPLES),
    "test8.xml": (IMPORTS, [("2011-01-01T16:00:00", 30, 30.0)]),
    "test9.xml": (IMPORTS, [("2011-01-01T17:00:00", 30, 30.0)]),
    "test10.xml": (REFUSED, NO_SAMPLES),
    "test11.xml": (REFUSED, NO_SAMPLES),
    "test12.xml": (REFUSED, NO_SAMPLES),
    "test13.xml": (IMPORTS, [("2011-01-01T21:00:00", 30, 30.0)]),
    "test14.xml": (IMPORTS, [("2011-01-01T22:00:00", 30, 30.0)]),
    "test15.xml": (REFUSED, NO_SAMPLES),
    "test18.xml": (IMPORTS, [("2011-12-02T11:00:00", 6, 70.0)]),
    "test19.xml": (IMPORTS, [("2011-12-02T12:00:00", 7, 70.0)]),
    "test20.xml": (IMPORTS, [("2011-12-02T13:00:00", 7, 70.0)]),
    "test21.xml": (REFUSED, NO_SAMPLES),
    "test22.xml": (REFUSED, NO_SAMPLES),
    "test23.xml": (REFUSED, NO_SAMPLES + r"; 1 more dive skipped\)$"),
    "TwoTimesTwo.ssrf": (REFUSED, NO_SAMPLES + r"; 3 more dives skipped\)$"),
    "DL7.xml": (IMPORTS, [("2018-01-02T10:10:00", 4, 10.0)]),
    "TestDiveDivelogsDE.xml": (IMPORTS, [("2011-05-17T11:01:00", 65, 24.69)]),
    "TestDiveSeabearHUDC.xml": (IMPORTS, [("2009-10-10T05:32:41", 95, 40.0)]),
    "00000023.DLF.new.xml": (IMPORTS, [("2018-09-08T11:16:52", 77, 1.8)]),
    "test-uddf-export-events.uddf": (IMPORTS, [("2026-08-23T12:00:00", 6, 30.0)]),
    "TestDiveDivingLog5.08.uddf": (IMPORTS, [("2011-05-17T11:01:00", 65, 24.69)]),
    "100.xml": (REFUSED, r"XML that is neither .*\(root element <SUUNTO>; not a dive log"),
    "TestDiveDM4.xml": (IMPORTS, [("2013-02-02T16:14:08", 179, 22.41)]),
    "test0.xml": (REFUSED, NO_SAMPLES),
    "test24.xml": (REFUSED, r"no <dive> in this Subsurface logbook$"),  # empty on purpose
    "test25.xml": (IMPORTS, [("2011-12-02T06:00:00", 6, 20.0)]),
    "test26.xml": (IMPORTS, [("2011-12-02T06:35:00", 6, 20.0)]),
    "test27.xml": (IMPORTS, [("2011-12-12T06:35:00", 6, 20.0)]),
    "test28.xml": (IMPORTS, [("2011-12-13T09:26:12", 39, 2.4)]),
    # Four dives sharing one diveid: four dives all the same.
    "test29.xml": (
        IMPORTS,
        [(f"2011-12-13T{hour:02d}:35:00", 6, 20.1) for hour in (6, 7, 8, 9)],
    ),
    "test30.xml": (IMPORTS, [("2013-12-28T06:56:12", 7, 25.0)]),
    # The divecomputer's own date and time, not the dive's (2012-01-08 15:30:03).
    "test31.xml": (IMPORTS, [("2014-01-09T14:22:03", 6, 15.0)]),
    "test32.xml": (IMPORTS, [("2014-03-15T21:44:06", 16, 15.0)]),
    "test33.xml": (IMPORTS, [("2014-03-15T23:44:06", 16, 15.0)]),
    "test34.xml": (IMPORTS, [("2014-04-01T06:00:00", 138, 2.9)]),
    "test35.xml": (IMPORTS, [("2014-04-01T07:00:00", 7, 70.0)]),
    "test38.xml": (REFUSED, NO_SAMPLES),
    "test43.xml": (IMPORTS, [("2014-01-09T14:22:03", 7, 15.0)]),
    "test44.xml": (IMPORTS, [("2014-01-09T14:22:03", 7, 15.0)]),
    "test47.xml": (IMPORTS, [("2015-10-05T08:45:25", 6, 13.716)]),
    "test48.xml": (REFUSED, NO_SAMPLES),
    # Unpadded dates (2015-1-1) are read; these three dives just have no profile.
    # (Two of them share number 1, so they are named by their place in the file.)
    "test50.xml": (
        REFUSED,
        r"\(dive #1 \(number 1\) divecomputer 1: no samples; 2 more dives skipped\)$",
    ),
    "test51.xml": (IMPORTS, [("2018-10-29T16:39:32", 47, 110.0)]),
    "vyper.xml": (
        IMPORTS,
        [("2017-02-03T06:59:41", 216, 26.57), ("2017-02-03T10:25:16", 198, 27.8)],
    ),
    "mergedVyperOstc.xml": (
        IMPORTS,
        [
            ("2017-02-03T06:58:00", 78, 26.097),
            ("2017-02-03T10:24:00", 72, 26.998),
            ("2017-02-03T06:59:41", 216, 26.57),
            ("2017-02-03T10:25:16", 198, 27.8),
        ],
    ),
    # Subsurface's merges of test47.xml and test48.xml (either order): the
    # divecomputer's own start, as in test47.xml.
    "test47+48.xml": (IMPORTS, [("2015-10-05T08:45:25", 6, 13.716)]),
    "test48+47.xml": (IMPORTS, [("2015-10-05T08:45:25", 6, 13.716)]),
    # A trip holding two dives; air pressure per dive (not read, not in the way).
    "TestAtmPress.xml": (
        IMPORTS,
        [("2019-04-09T09:15:16", 5, 4.488), ("2019-04-10T08:14:01", 10, 7.785)],
    ),
    # Heart rate and bearing on the samples; one sample above the surface (-0.019 m).
    "test36.xml": (IMPORTS, [("2014-04-02T07:00:00", 444, 3.66)]),
    # The first format (<dives> root, <program> element, samples in <dive>); water
    # temperatures jumping 5-35 C on purpose.
    "test16.xml": (IMPORTS, [("2011-12-02T01:00:00", 887, 36.27)]),
    "test17.xml": (IMPORTS, [("2011-12-02T10:00:00", 887, 36.27)]),  # test16, narrow temps
    # Subsurface's reading of Suunto DM5's database (the DM4 test's first dive and
    # three more), written in file order, not start order.
    "TestDiveDM5.xml": (
        IMPORTS,
        [
            ("2013-02-02T16:14:08", 179, 22.41),
            ("2013-02-02T13:44:21", 184, 21.8),
            ("2013-02-02T10:53:54", 199, 22.04),
            ("2013-02-02T08:21:50", 183, 28.74),
        ],
    ),
    # Subsurface's V2 test file (a CCR dive, OSTC 3, unpadded date 2014-4-1), parsed by
    # its testparse; 2-second samples 0:02 to 82:50.
    "test40.xml": (IMPORTS, [("2014-04-01T10:00:00", 2485, 38.974)]),
    # Its V3 twin (divesites, a padded date a day later); the same samples.
    "test42.xml": (IMPORTS, [("2014-04-02T10:00:00", 2485, 38.974)]),
    # Subsurface's reading of test-apd-inspiration.uddf (below): one dive (the UDDF's
    # placeholder dive is not one), samples partly out of time order (19:00 before
    # 18:59) and repeated, as the APD logger wrote them.
    "test-apd-inspiration-reference.xml": (IMPORTS, [("2022-04-24T10:30:58", 695, 60.2)]),
    # AP DiveSight's UDDF 3.3 of an APD Inspiration CCR dive: a placeholder <dive
    # id="previous_dive"> (skipped, no start) and the dive, 695 waypoints with divetimes
    # in tenths of a second, some out of order (1140.0 before 1139.0), sorted on import.
    "test-apd-inspiration.uddf": (IMPORTS, [("2022-04-24T10:30:58", 695, 60.2)]),
    # Subsurface's UDDF export of test40.xml (2-second waypoints, depths in whole
    # centimetres, temperatures in kelvin only where test40.xml has one).
    "test40.uddf": (IMPORTS, [("2014-04-01T10:00:00", 2485, 38.97)]),
    # Subsurface's reading of test41.csv (four dives without a profile, skipped),
    # TestDivingLog4.1.1.sql (dive 417), test40.xml and test42.xml.
    "test40-42.xml": (
        IMPORTS,
        [
            ("2015-05-23T13:23:00", 689, 79.57),
            ("2014-04-01T10:00:00", 2485, 38.974),
            ("2014-04-02T10:00:00", 2485, 38.974),
        ],
    ),
    # Subsurface's reading of Seabear H3 and T1 CSV logs: the same four or five dives
    # from two computers (same starts, told apart by model), one a 1-second freedive.
    "TestDiveSeabearNewFormat.xml": (
        IMPORTS,
        [
            ("2012-10-01T06:22:00", 198, 69.9),
            ("2012-10-01T06:49:00", 198, 69.9),
            ("2012-10-01T07:07:00", 925, 70.1),
            ("2012-10-01T07:24:00", 198, 69.9),
            ("2012-10-01T06:02:00", 198, 69.9),
            ("2012-10-01T06:22:00", 198, 69.9),
            ("2012-10-01T06:49:00", 198, 69.9),
            ("2012-10-01T07:07:00", 925, 70.1),
            ("2012-10-01T07:24:00", 198, 69.9),
        ],
    ),
    # Subsurface's renumbering test: test47.xml's dive from a second file (another
    # site), then with a second dive; the divecomputer's own starts, as in test47.xml.
    "test47b.xml": (IMPORTS, [("2015-10-05T08:45:25", 6, 13.716)]),
    "test47c.xml": (
        IMPORTS,
        [("2015-10-05T08:45:25", 6, 13.716), ("2015-10-05T08:48:05", 6, 13.716)],
    ),
    # Its tank-sensor tests: four CCR dives (tank sensor mappings, pressure2 on one
    # sample); the same dives from a second computer; and Subsurface's merge of the two
    # files, each dive holding both computers (eight profiles, in dive order).
    "test-tank-sensor-mapping.xml": (
        IMPORTS,
        [
            ("2025-03-11T20:46:51", 12, 15.0),
            ("2025-03-11T20:47:03", 14, 15.0),
            ("2025-03-11T20:47:27", 15, 15.0),
            ("2025-03-11T20:47:33", 15, 15.0),
        ],
    ),
    "test-tank-sensor-mapping-merge.xml": (
        IMPORTS,
        [
            ("2025-03-11T20:46:51", 12, 15.0),
            ("2025-03-11T20:47:03", 14, 15.0),
            ("2025-03-11T20:47:27", 15, 15.0),
            ("2025-03-11T20:47:33", 15, 15.0),
        ],
    ),
    "merged-tank-sensors.xml": (
        IMPORTS,
        [
            (start, samples, 15.0)
            for start, samples in (
                ("2025-03-11T20:46:51", 12),
                ("2025-03-11T20:47:03", 14),
                ("2025-03-11T20:47:27", 15),
                ("2025-03-11T20:47:33", 15),
            )
            for _computer in (1, 2)
        ],
    ),
    # Subsurface's readings of Suunto app JSON logs (the .json beside them, not ours).
    # All but nautic_multigas write every sample twice at the same time (once with its
    # extra values, once depth only); both copies are read, so times repeat.
    "suunto_ocean_gf.xml": (IMPORTS, [("2025-06-01T09:00:00", 10, 20.0)]),
    "suunto_ocean_gf_fit_override.xml": (IMPORTS, [("2025-06-01T09:00:00", 10, 20.0)]),
    "suunto_eon_core_multigas.xml": (IMPORTS, [("2025-06-01T09:00:00", 22, 20.0)]),
    "suunto_nautic_multigas.xml": (IMPORTS, [("2025-12-27T15:56:17", 79, 21.14)]),
    "suunto_ocean_nitrox.xml": (IMPORTS, [("2026-05-15T10:40:49", 836, 10.59)]),
    "suunto_eon_core_nitrox.xml": (IMPORTS, [("2024-10-06T00:33:51", 796, 22.65)]),
    "suunto_ocean_air.xml": (IMPORTS, [("2026-01-13T06:05:31", 664, 23.12)]),
    # The same computer and dive as nautic_multigas, whose 79 samples are its first 12:20
    # (checked below), but an hour earlier: nautic_multigas applies its 'Time offset
    # from UTC' of 3600 s, this reading does not.
    "suunto_nautic_sidemount.xml": (IMPORTS, [("2025-12-27T14:56:17", 420, 21.14)]),
    # Subsurface's import of a Poseidon MkVI CSV log ('subsurface-import' version 2,
    # times without 'min'): 1702 samples, the first seven with an empty temperature
    # (temp=' C'), kept without one as Subsurface keeps them.
    "Poseidon_MkVILog.xml": (IMPORTS, [("2011-06-14T11:20:00", 1702, 35.5)]),
    # Subsurface's "a bit of everything" logbook: 18 <dive>s in 11 trips, 26 divecomputers
    # (one profile each, in file order, so not in start order): up to three computers on
    # one dive (Uemis, OSTC 2N, Petrel), manual and planned dives (the planner's notes in
    # escaped HTML, negative planned pressures), a CCR dive, a picture, extradata. Every
    # dive has a date and every divecomputer samples: none is skipped.
    "abitofeverything.ssrf": (
        IMPORTS,
        [
            ("2010-12-05T11:26:00", 52, 11.28),
            ("2011-01-01T17:00:00", 30, 30.0),
            ("2011-10-21T12:58:49", 791, 35.6),
            ("2011-10-22T09:12:55", 828, 40.9),
            ("2011-10-22T13:33:50", 839, 30.67),
            ("2011-12-02T11:00:00", 6, 70.0),
            ("2011-12-02T12:00:00", 7, 70.0),
            ("2011-12-02T13:00:00", 7, 70.0),
            ("2014-01-09T14:22:03", 7, 15.0),  # the divecomputer's own date, as test31
            ("2013-06-01T12:24:09", 755, 24.06),
            ("2013-06-01T12:22:00", 402, 24.067),
            ("2013-06-01T12:23:41", 376, 24.293),
            ("2013-06-04T10:04:18", 731, 31.18),
            ("2013-06-04T10:02:00", 390, 31.235),
            ("2013-06-04T10:03:06", 371, 31.151),
            ("2013-06-04T12:28:06", 708, 27.54),
            ("2013-06-04T12:26:00", 379, 27.76),
            ("2013-06-04T12:26:48", 360, 27.828),
            ("2013-12-28T06:56:12", 7, 25.0),
            ("2014-03-15T21:44:06", 16, 15.0),
            ("2014-04-01T07:00:00", 7, 70.0),
            ("2014-04-02T10:00:00", 2485, 38.974),  # test40.xml's CCR dive
            ("2014-09-21T14:25:00", 1073, 44.444),
            ("2014-09-21T14:22:00", 254, 45.224),
            ("2014-09-21T14:23:40", 224, 45.446),
            ("2020-05-03T14:24:14", 19, 60.0),
        ],
    ),
}

# abitofeverything.ssrf: the divecomputers whose recorded <depth max> is not the deepest
# sample within 0.01 m, with that maximum. The dive computer's own maximum falls between
# the samples it kept (Uemis every 4-5 s, OSTC 2N / Petrel every 10 s, the CCR OSTC 3
# every 2 s); one Petrel's deepest 10-s sample (45.446 m) is below its recorded 45.415 m.
ABITOFEVERYTHING_OTHER_MAXIMUM = {
    "2011-10-21T12:58:49": 36.01,
    "2011-10-22T09:12:55": 41.39,
    "2011-10-22T13:33:50": 31.0,
    "2013-06-01T12:24:09": 24.43,
    "2013-06-01T12:22:00": 24.08,
    "2013-06-01T12:23:41": 24.384,
    "2013-06-04T10:04:18": 31.52,
    "2013-06-04T10:02:00": 31.27,
    "2013-06-04T10:03:06": 31.699,
    "2013-06-04T12:28:06": 28.17,
    "2013-06-04T12:26:48": 28.042,
    "2014-04-02T10:00:00": 38.99,
    "2014-09-21T14:23:40": 45.415,
}

# The same dives read by another program and by Subsurface: our reading of the files
# on the left must give the profiles of our reading of Subsurface's file on the right.
# Diving Log's UDDF export of a dive and Subsurface's import of divelogs.de's export of
# it; ostc.xml (../shared/data) and vyper.xml, and Subsurface's file holding both.
SAME_DIVES = {
    ("TestDiveDivingLog5.08.uddf",): "TestDiveDivelogsDE.xml",
    ("../shared/ostc.xml", "vyper.xml"): "mergedVyperOstc.xml",
}

# Files holding the same profile under two versions of Subsurface's format, or the same
# dive written again by Subsurface's renumbering test (another site, a second dive).
SAME_PROFILE = [
    ("test40.xml", "test42.xml"),
    ("test16.xml", "test17.xml"),
    ("test47.xml", "test47b.xml"),
]


def corpus_files() -> list[str]:
    return sorted(
        p.name for p in CORPUS.iterdir() if p.suffix.lower() in (".xml", ".ssrf", ".uddf")
    )


def test_every_corpus_file_has_an_expectation() -> None:
    assert corpus_files() == sorted(CORPUS_EXPECTED)


@pytest.mark.parametrize("name", sorted(CORPUS_EXPECTED))
def test_corpus_file(name: str, tmp_path: Path) -> None:
    kind, expected = CORPUS_EXPECTED[name]
    path = CORPUS / name
    if kind == REFUSED:
        with pytest.raises(InputError) as caught:
            read_logbook(path)
        message = str(caught.value)
        assert message.startswith(f"{path}: ") and "\n" not in message
        assert re.search(str(expected), message), message
        out = tmp_path / "dives"
        with pytest.raises(InputError):
            import_logbook(path, out)
        assert not out.exists()  # nothing written for a refused file
        return
    dives = read_logbook(path)
    got = [(d.start_iso, int(d.stamps_s.size), d.max_depth_m) for d in dives]
    assert [(s, n) for s, n, _ in got] == [(s, n) for s, n, _ in expected]  # type: ignore[attr-defined]
    assert [m for _, _, m in got] == pytest.approx([m for _, _, m in expected])  # type: ignore[attr-defined]
    assert all(np.all(np.diff(d.stamps_s) >= 0) for d in dives)
    written = import_logbook(path, tmp_path / "dives")
    assert len(written) == len(dives)


def written_by_subsurface(path: Path) -> bool:
    root = ET.parse(path).getroot()
    return root.tag == "divelog" and root.get("program") == "subsurface"


@pytest.mark.parametrize(
    "name",
    [
        n
        for n in sorted(CORPUS_EXPECTED)
        if CORPUS_EXPECTED[n][0] == IMPORTS
        and n.endswith(".xml")
        and written_by_subsurface(CORPUS / n)
    ],
)
def test_corpus_matches_subsurface_summary(name: str) -> None:
    """Files Subsurface wrote: our samples are its samples, within its recorded maximum."""
    path = CORPUS / name
    theirs = subsurface_reading(path)
    ours = read_logbook(path)
    assert [d.stamps_s.size for d in ours] == [n for n, _, _ in theirs]
    for dive, (_, deepest, recorded) in zip(ours, theirs, strict=True):
        assert dive.max_depth_m == pytest.approx(deepest, abs=1e-9)
        assert dive.max_depth_m <= recorded + 0.0005  # Subsurface keeps whole millimetres


def corpus_path(name: str) -> Path:
    return DIVELOGS / name.removeprefix("../shared/") if name.startswith("../") else CORPUS / name


@pytest.mark.parametrize(("names", "reference"), sorted(SAME_DIVES.items()))
def test_corpus_same_dives_as_subsurface_read_them(names: tuple[str, ...], reference: str) -> None:
    ours: list[DiveProfile] = [d for name in names for d in read_logbook(corpus_path(name))]
    theirs = read_logbook(CORPUS / reference)
    assert len(ours) == len(theirs)
    for a, b in zip(ours, theirs, strict=True):
        assert a.start_iso == b.start_iso
        if a.model and b.model:  # both name the dive computer (Diving Log names itself)
            assert (a.model, a.serial) == (b.model, b.serial)
        np.testing.assert_array_equal(a.stamps_s, b.stamps_s)
        np.testing.assert_allclose(a.depth_m, b.depth_m, atol=1e-9)


def test_merged_tank_sensors_is_both_files_dives() -> None:
    """Subsurface merges test-tank-sensor-mapping.xml and its twin from a second computer
    into merged-tank-sensors.xml: the merged file's profiles are the two files' profiles,
    one per (start, computer), with the same samples."""

    def key(dive: DiveProfile) -> tuple[str, str]:
        return (dive.start_iso, dive.model)

    names = ("test-tank-sensor-mapping.xml", "test-tank-sensor-mapping-merge.xml")
    ours = sorted((d for name in names for d in read_logbook(CORPUS / name)), key=key)
    theirs = sorted(read_logbook(CORPUS / "merged-tank-sensors.xml"), key=key)
    assert [key(d) for d in ours] == [key(d) for d in theirs]
    assert len({key(d) for d in theirs}) == len(theirs) == 8
    for a, b in zip(ours, theirs, strict=True):
        np.testing.assert_array_equal(a.stamps_s, b.stamps_s)
        np.testing.assert_array_equal(a.depth_m, b.depth_m)


def test_suunto_nautic_readings_share_a_profile() -> None:
    """Subsurface's two readings of one Suunto Nautic dive: the multigas one is the first
    12:20 of the sidemount one (whose samples come twice), one hour later on the clock."""
    (short,) = read_logbook(CORPUS / "suunto_nautic_multigas.xml")
    (full,) = read_logbook(CORPUS / "suunto_nautic_sidemount.xml")
    assert (short.model, short.serial) == (full.model, full.serial)
    np.testing.assert_array_equal(full.stamps_s[0::2], full.stamps_s[1::2])
    once = slice(0, 2 * short.stamps_s.size, 2)
    np.testing.assert_array_equal(short.depth_m, full.depth_m[once])
    np.testing.assert_array_equal(short.stamps_s - 3600.0, full.stamps_s[once])


@pytest.mark.parametrize(("first", "second"), SAME_PROFILE)
def test_corpus_same_profile_in_two_spellings(first: str, second: str) -> None:
    (a,) = read_logbook(CORPUS / first)
    (b,) = read_logbook(CORPUS / second)
    np.testing.assert_array_equal(a.stamps_s - a.stamps_s[0], b.stamps_s - b.stamps_s[0])
    np.testing.assert_array_equal(a.depth_m, b.depth_m)


def test_test47c_is_test47b_and_one_more_dive() -> None:
    """test47c.xml (Subsurface's merge-and-append renumbering input) holds test47b's dive
    unchanged and a second dive with the same profile 2 min 40 s later."""
    (b,) = read_logbook(CORPUS / "test47b.xml")
    first, second = read_logbook(CORPUS / "test47c.xml")
    assert (first.start_iso, first.fingerprint) == (b.start_iso, b.fingerprint)
    np.testing.assert_array_equal(first.stamps_s, b.stamps_s)
    np.testing.assert_array_equal(second.stamps_s - 160.0, b.stamps_s)
    np.testing.assert_array_equal(second.depth_m, b.depth_m)
    assert second.fingerprint != first.fingerprint


def test_test40_and_test42_match_subsurface_reading() -> None:
    """Subsurface's testparse reads test40.xml (V2) and test42.xml (V3) and saves
    test40-42.xml: our reading of each file gives the dive of its reading."""
    theirs = {d.start_iso: d for d in read_logbook(CORPUS / "test40-42.xml")}
    for name in ("test40.xml", "test42.xml"):
        (ours,) = read_logbook(CORPUS / name)
        reference = theirs[ours.start_iso]
        # (Not the fingerprint: in test40-42.xml both dives carry diveid 76543210 at
        # different starts, so each gets an id of its own.)
        assert (ours.model, ours.serial) == (reference.model, reference.serial)
        np.testing.assert_array_equal(ours.stamps_s, reference.stamps_s)
        np.testing.assert_array_equal(ours.depth_m, reference.depth_m)
        np.testing.assert_array_equal(ours.temperature_c, reference.temperature_c)


def test_apd_inspiration_uddf_matches_subsurface_reading() -> None:
    """Subsurface's testparse reads test-apd-inspiration.uddf and saves
    test-apd-inspiration-reference.xml: our reading of the UDDF gives that reading's dive.
    Subsurface keeps whole seconds (148.1 s is 2:28) and writes depths in metres as read;
    out-of-order waypoints are sorted by their own time, so samples are compared per
    second. The UDDF's greatestdepth, 60.4 m, is Subsurface's recorded maximum."""
    reference = CORPUS / "test-apd-inspiration-reference.xml"
    ours = read_logbook(CORPUS / "test-apd-inspiration.uddf")
    theirs = subsurface_reading(reference)
    assert len(ours) == len(theirs) == 1
    (dive,), ((samples, deepest, recorded),) = ours, theirs
    (reference_dive,) = read_logbook(reference)
    assert dive.start_iso == reference_dive.start_iso == "2022-04-24T10:30:58"
    assert dive.model == reference_dive.model == "AP DiveSight"
    assert dive.stamps_s.size == samples == 695
    assert abs(dive.max_depth_m - deepest) <= 0.01
    assert dive.max_depth_m <= recorded == 60.4
    np.testing.assert_allclose(dive.stamps_s, reference_dive.stamps_s, rtol=0, atol=0.5)

    def per_second(profile: DiveProfile) -> list[tuple[int, float]]:
        seconds = np.floor(profile.stamps_s - profile.stamps_s[0] + 1e-3).astype(int)
        return sorted(zip(seconds.tolist(), np.round(profile.depth_m, 3).tolist(), strict=True))

    assert per_second(dive) == per_second(reference_dive)
    # Subsurface writes the kelvin temperatures to 0.1 C, and only where they change.
    written = ~np.isnan(reference_dive.temperature_c)
    np.testing.assert_allclose(
        dive.temperature_c[written], reference_dive.temperature_c[written], rtol=0, atol=0.051
    )


def test_test40_uddf_is_test40_xml_at_centimetres() -> None:
    """test40.uddf is not read by Subsurface's tests (its exportUDDF test exports
    test40.xml to a file of its own and compares two exports), so there is no reading of
    it to compare against; its content is test40.xml's dive: the same start and 2-second
    samples, depths rounded to whole centimetres, temperatures on the same samples."""
    (uddf,) = read_logbook(CORPUS / "test40.uddf")
    (xml,) = read_logbook(CORPUS / "test40.xml")
    assert uddf.start_iso == xml.start_iso
    np.testing.assert_array_equal(uddf.stamps_s, xml.stamps_s)
    np.testing.assert_allclose(uddf.depth_m, xml.depth_m, rtol=0, atol=0.005 + 1e-9)
    np.testing.assert_array_equal(np.isnan(uddf.temperature_c), np.isnan(xml.temperature_c))
    np.testing.assert_allclose(uddf.temperature_c, xml.temperature_c, rtol=0, atol=1e-9)


def test_abitofeverything_against_its_recorded_maxima() -> None:
    """Every <dive> of abitofeverything.ssrf has a date and samples on each divecomputer
    (none to skip); our profiles are its divecomputers, sample for sample, and the
    deepest sample is the recorded <depth max> within 0.01 m except where listed."""
    path = CORPUS / "abitofeverything.ssrf"
    root = ET.parse(path).getroot()
    dives = list(root.iter("dive"))
    assert len(dives) == 18
    assert all(d.get("date") for d in dives)
    assert all(c.findall("sample") for d in dives for c in d.findall("divecomputer"))
    theirs = subsurface_reading(path)
    ours = read_logbook(path)
    assert len(ours) == len(theirs) == 26
    listed = dict(ABITOFEVERYTHING_OTHER_MAXIMUM)
    for dive, (samples, deepest, recorded) in zip(ours, theirs, strict=True):
        assert dive.stamps_s.size == samples
        assert dive.max_depth_m == pytest.approx(deepest, abs=1e-9)
        other = listed.pop(dive.start_iso, None)
        if other is None:
            assert dive.max_depth_m == pytest.approx(recorded, abs=0.01)
        else:
            assert recorded == other
            assert abs(dive.max_depth_m - recorded) > 0.01
    assert not listed
