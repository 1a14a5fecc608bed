"""Logbook importers against every real file in ../shared/data/divelogs, and refusals."""

from __future__ import annotations

import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from field.divecomputer.importers import (
    IMPORTERS,
    detect_format,
    import_logbook,
    read_logbook,
)
from shared.errors import InputError
from shared.formats.diveprofile import read_dive_folder, read_dive_index

REPO = Path(__file__).resolve().parents[3]
NAN = math.nan

# file, dive index: start, model, serial, samples, (t0 s, depth0, temp0), (t_end, depth, temp),
# max depth (deepest sample), samples with a temperature, sample interval
EXPECTED = {
    ("test42.uddf", 0): (
        "2014-04-02T10:00:00", "Subsurface Divelog", "", 2485,
        (2.0, 2.34, NAN), (4970.0, 0.24, NAN), 38.97, 153, 2.0,
    ),
    ("ostc.xml", 0): (
        "2017-02-03T06:58:00", "Heinrichs Weikamp OSTC Sport", "10321", 78,
        (2.0, 2.465, NAN), (4616.0, 0.01, NAN), 26.097, 10, 60.0,
    ),
    ("ostc.xml", 1): (
        "2017-02-03T10:24:00", "Heinrichs Weikamp OSTC Sport", "10321", 72,
        (2.0, 2.505, NAN), (4246.0, 0.0, NAN), 26.998, 14, 60.0,
    ),
    ("shearwater-perdix2-dive68.uddf", 0): (
        "2025-01-20T17:45:38", "Shearwater Perdix 2", "AF0B4DD1", 252,
        (0.0, 1.00609756, 8.0), (2510.0, 0.0, 8.0), 12.5914631, 252, 10.0,
    ),
    ("shearwater-petrel3-dive88.csv", 0): (
        "2025-10-31T11:51:49", "Shearwater Petrel 3", "B2F10222", 668,
        (0.0, 1.3, 28.0), (6670.0, 0.0, 24.0), 53.6, 668, 10.0,
    ),
}  # fmt: skip


def same(a: float, b: float) -> bool:
    return (math.isnan(a) and math.isnan(b)) or a == pytest.approx(b, abs=1e-9)


@pytest.mark.parametrize(("name", "index"), sorted(EXPECTED))
def test_real_logbooks(shared_data: Path, name: str, index: int) -> None:
    start, model, serial, count, first, last, max_depth, with_temp, interval = EXPECTED[
        (name, index)
    ]
    dive = read_logbook(shared_data / "divelogs" / name)[index]
    assert (dive.start_iso, dive.model, dive.serial) == (start, model, serial)
    assert dive.stamps_s.size == count and dive.sample_interval_s == interval
    got_first = (dive.stamps_s[0] - dive.start_s, dive.depth_m[0], dive.temperature_c[0])
    got_last = (dive.stamps_s[-1] - dive.start_s, dive.depth_m[-1], dive.temperature_c[-1])
    assert all(same(g, w) for g, w in zip(got_first + got_last, first + last, strict=True))
    assert dive.max_depth_m == pytest.approx(max_depth)
    assert dive.duration_s == last[0]
    assert int(np.isfinite(dive.temperature_c).sum()) == with_temp
    assert np.all(np.diff(dive.stamps_s) > 0)


def test_every_real_file_is_covered(shared_data: Path) -> None:
    names = {p.name for p in (shared_data / "divelogs").iterdir()}
    assert names == {name for name, _ in EXPECTED} | {"test-42-uddf-import-reference.xml"}


def test_uddf_matches_subsurface_reading(shared_data: Path) -> None:
    folder = shared_data / "divelogs"
    (ours,) = read_logbook(folder / "test42.uddf")
    (reference,) = read_logbook(folder / "test-42-uddf-import-reference.xml")
    assert ours.start_iso == reference.start_iso and ours.model == reference.model
    np.testing.assert_array_equal(ours.stamps_s, reference.stamps_s)
    np.testing.assert_array_equal(ours.depth_m, reference.depth_m)
    np.testing.assert_array_equal(ours.temperature_c, reference.temperature_c)  # NaN too
    # Cross-check the reference's own summary: its duration is the UDDF <diveduration>.
    text = (folder / "test-42-uddf-import-reference.xml").read_text()
    assert (
        "duration='77:54 min'" in text
        and "<diveduration>4674</diveduration>" in (folder / "test42.uddf").read_text()
    )


def test_shearwater_fingerprint_is_the_start_time(shared_data: Path) -> None:
    (dive,) = read_logbook(shared_data / "divelogs" / "shearwater-petrel3-dive88.csv")
    assert int(dive.fingerprint, 16) == int(dive.start_s)


def test_uddf_without_namespace(shared_data: Path, tmp_path: Path) -> None:
    text = (shared_data / "divelogs" / "shearwater-perdix2-dive68.uddf").read_text()
    bare = re.sub(r'\sxmlns(:\w+)?="[^"]*"', "", text).replace("xsi:", "")
    path = tmp_path / "bare.uddf"
    path.write_text(bare)
    (with_ns,) = read_logbook(shared_data / "divelogs" / "shearwater-perdix2-dive68.uddf")
    (without,) = read_logbook(path)
    np.testing.assert_array_equal(with_ns.depth_m, without.depth_m)
    assert without.serial == "AF0B4DD1"


def imperial_copy(source: Path, target: Path, *, units_in_headers: bool) -> None:
    lines = source.read_text().splitlines()
    summary = lines[0].split(",")
    values = lines[1].split(",")
    values[summary.index("Imperial Units")] = "True" if not units_in_headers else "False"
    header = lines[2].split(",")
    depth, temp = header.index("Depth"), header.index("Water Temp")
    if units_in_headers:
        header[depth], header[temp] = "Depth (ft)", "Water Temp (F)"
    out = [lines[0], ",".join(values), ",".join(header)]
    for line in lines[3:]:
        cells = line.split(",")
        cells[depth] = repr(float(cells[depth]) / 0.3048)
        cells[temp] = repr(float(cells[temp]) * 9 / 5 + 32)
        out.append(",".join(cells))
    target.write_text("\n".join(out) + "\n")


@pytest.mark.parametrize("units_in_headers", [False, True])
def test_shearwater_csv_imperial(shared_data: Path, tmp_path: Path, units_in_headers: bool) -> None:
    source = shared_data / "divelogs" / "shearwater-petrel3-dive88.csv"
    imperial = tmp_path / "imperial.csv"
    imperial_copy(source, imperial, units_in_headers=units_in_headers)
    (metric_dive,) = read_logbook(source)
    (imperial_dive,) = read_logbook(imperial)
    np.testing.assert_allclose(imperial_dive.depth_m, metric_dive.depth_m, atol=1e-9)
    np.testing.assert_allclose(imperial_dive.temperature_c, metric_dive.temperature_c, atol=1e-9)


SUBSURFACE_TRIP = """<divelog program='subsurface' version='3'>
<dives>
<trip date='2020-05-01' time='08:00:00'>
<dive number='7' date='2020-05-01' time='09:00:00'>
  <divecomputer model='A' deviceid='1' diveid='0000abcd'>
  <sample time='0:10 min' depth='33.0 ft' temp='68.0 F' />
  <sample time='1:10 min' depth='12.0 m' temp='290.15 K' />
  </divecomputer>
  <divecomputer model='B' date='2020-05-01' time='09:00:30'>
  <sample time='1:00:00' depth='1.5 m' />
  </divecomputer>
</dive>
</trip>
</dives>
</divelog>
"""


def test_subsurface_trips_and_every_divecomputer(tmp_path: Path) -> None:
    path = tmp_path / "log.ssrf"
    path.write_text(SUBSURFACE_TRIP)
    first, second = read_logbook(path)
    assert first.fingerprint == "0000ABCD" and first.model == "A"
    assert first.depth_m[0] == pytest.approx(33.0 * 0.3048)
    assert first.temperature_c.tolist() == [pytest.approx(20.0), 17.0]
    assert second.model == "B" and second.start_iso == "2020-05-01T09:00:30"
    assert second.stamps_s[0] - second.start_s == 3600.0
    assert second.sample_interval_s is None
    out = tmp_path / "dives"
    assert len(import_logbook(path, out)) == 2
    assert import_logbook(path, out) == []  # repeated import adds nothing
    assert len(read_dive_index(out)) == 2


BILLION_LAUGHS = """<?xml version="1.0"?>
<!DOCTYPE lolz [
 <!ENTITY lol "lol">
 <!ENTITY lol1 "&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;">
 <!ENTITY lol2 "&lol1;&lol1;&lol1;&lol1;&lol1;&lol1;&lol1;&lol1;&lol1;&lol1;">
]>
<uddf><generator><name>&lol2;</name></generator></uddf>
"""
EXTERNAL = """<?xml version="1.0"?>
<!DOCTYPE divelog [<!ENTITY secret SYSTEM "file:///etc/passwd">]>
<divelog><dives><dive date='2020-01-01'><notes>&secret;</notes></dive></dives></divelog>
"""


@pytest.mark.parametrize(
    ("name", "content", "match"),
    [
        ("lol.uddf", BILLION_LAUGHS, "refused unsafe XML"),
        ("ext.xml", EXTERNAL, "refused unsafe XML"),
        ("broken.uddf", "<uddf><dive>", r"broken.uddf:1:\d+: malformed XML"),
        ("other.xml", "<gpx></gpx>", r"neither Subsurface .* \(root element <gpx>"),
        ("notes.txt", "hello", "unknown logbook type .txt"),
        ("empty.uddf", "<uddf></uddf>", "no <dive>"),
        ("empty.ssrf", "<divelog></divelog>", "no <dive>"),
        ("wrongroot.ssrf", "<uddf></uddf>", "expected Subsurface's <divelog>"),
        ("wrongroot.uddf", "<divelog/>", r"expected <uddf>"),
        (
            "nodate.uddf",
            "<uddf><dive><samples/></dive></uddf>",
            r"no importable dive \(dive 1: no informationbeforedive/datetime\)",
        ),
        (
            "baddepth.ssrf",
            "<divelog><dive date='2020-01-01'><sample time='0:10 min' depth='deep' /></dive>"
            "</divelog>",
            r"no importable dive \(dive 1: no readable sample; first: sample at 0:10 min: 'deep'",
        ),
        (
            "badunit.ssrf",
            "<divelog><dive date='2020-01-01'><sample time='0:10 min' depth='3 yd' /></dive>"
            "</divelog>",
            "depth unit 'yd' in '3 yd'",
        ),
        (
            "notime.ssrf",
            "<divelog><dive date='2020-01-01'><sample depth='3 m' /></dive></divelog>",
            "sample 1: no time",
        ),
        (
            "badtime.ssrf",
            "<divelog><dive date='2020-01-01'><sample time='x:y min' depth='3 m'/></dive>"
            "</divelog>",
            "time 'x:y min' is not mm:ss",
        ),
        (
            "nodate.ssrf",
            "<divelog><dive><sample time='1:00 min'/></dive></divelog>",
            r"nodate.ssrf: no importable dive \(dive 1: no date\)$",
        ),
        (
            "baddate.ssrf",
            "<divelog><dive date='May 1'><sample time='1:00 min'/></dive></divelog>",
            "date 'May 1' is not y-m-d or d.m.y",
        ),
        (
            "nowaypointtime.uddf",
            "<uddf><dive><informationbeforedive><datetime>2020-01-01T10:00:00</datetime>"
            "</informationbeforedive><samples><waypoint><depth>3</depth></waypoint></samples>"
            "</dive></uddf>",
            r"dive 1: no readable sample; first: waypoint 1: no divetime",
        ),
        (
            "badnumber.uddf",
            "<uddf><dive><informationbeforedive><datetime>2020-01-01</datetime>"
            "</informationbeforedive><samples><waypoint><divetime>1</divetime><depth>x</depth>"
            "</waypoint></samples></dive></uddf>",
            "'x' is not a number",
        ),
        ("plain.csv", "a,b\n1,2\n3,4\n", "not a Shearwater Cloud CSV"),
    ],
)
def test_refusals(tmp_path: Path, name: str, content: str, match: str) -> None:
    path = tmp_path / name
    path.write_text(content)
    with pytest.raises(InputError, match=match):
        read_logbook(path)


def test_csv_refusals(shared_data: Path, tmp_path: Path) -> None:
    lines = (shared_data / "divelogs" / "shearwater-petrel3-dive88.csv").read_text().splitlines()
    bad_date = tmp_path / "date.csv"
    bad_date.write_text(
        "\n".join([lines[0], lines[1].replace("10/31/2025", "31.10.2025"), *lines[2:]])
    )
    with pytest.raises(InputError, match=r"start date '31\.10\.2025"):
        read_logbook(bad_date)
    bad_cell = tmp_path / "cell.csv"
    bad_cell.write_text("\n".join([*lines[:3], "10,deep" + lines[3][len("0,1.3") :]]))
    with pytest.raises(
        InputError, match=r"cell.csv: no readable sample line \(line 4: 'deep' is not"
    ):
        read_logbook(bad_cell)
    no_time = tmp_path / "notime.csv"
    no_time.write_text("\n".join([*lines[:3], "N/A" + lines[3][1:]]))
    with pytest.raises(
        InputError, match=r"notime\.csv: no readable sample line \(line 4: sample without"
    ):
        read_logbook(no_time)
    no_depth = tmp_path / "nodepth.csv"
    no_depth.write_text("\n".join([*lines[:2], "Time (sec),Temp", "0,1"]))
    with pytest.raises(InputError, match=r"nodepth.csv:3: sample header"):
        read_logbook(no_depth)
    binary = tmp_path / "binary.csv"
    binary.write_bytes(b"\xff\xfe\xfa")
    with pytest.raises(InputError, match="not UTF-8"):
        read_logbook(binary)


def test_registry_and_detection(tmp_path: Path) -> None:
    assert set(IMPORTERS) == {"subsurface", "uddf", "shearwater-csv"}
    assert detect_format(Path("x.UDDF")) == "uddf"
    assert detect_format(Path("x.ssrf")) == "subsurface"
    with pytest.raises(InputError, match="no such logbook"):
        read_logbook(tmp_path / "missing.xml")
    path = tmp_path / "a.xml"
    path.write_text(SUBSURFACE_TRIP)
    with pytest.raises(InputError, match="--format 'gpx'"):
        read_logbook(path, format_name="gpx")
    with pytest.raises(InputError, match="cannot read"):
        detect_format(tmp_path / "missing.xml")


def test_cli_import(shared_data: Path, tmp_path: Path) -> None:
    out = tmp_path / "dives"
    for name in ("ostc.xml", "test42.uddf", "shearwater-petrel3-dive88.csv"):
        command = [
            sys.executable, "-m", "field.cli", "dc", "import",
            str(shared_data / "divelogs" / name), "--out", str(out),
        ]  # fmt: skip
        done = subprocess.run(command, cwd=REPO, capture_output=True, text=True, timeout=60)
        assert done.returncode == 0, done.stderr
    dives = read_dive_folder(out)
    assert [d.stamps_s.size for d in dives] == [2485, 78, 72, 668]  # sorted by start
    bad = subprocess.run(
        [sys.executable, "-m", "field.cli", "dc", "import", str(tmp_path / "x.txt"), "--out", "o"],
        cwd=REPO, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert bad.returncode == 1 and "no such logbook file" in bad.stderr


# --------------------------------------------------------------- what real writers spell

UNPADDED = """<divelog program='subsurface' version='3'><dives>
<dive number='1' date='2014-4-1' time='10:0:0' duration='30:00 min'>
  <divecomputer model='Suunto Vyper' diveid='0a0b0c0d'>
  <sample time='0:10 min' depth='3,5 m' temp='15.0 C' />
  <sample time='1:00 min' depth='12.3 m' temp='-60.0 C' />
  <sample time='1:30 min' depth='twelve' />
  <sample time='2:00 min'><depth>10.0 m</depth><temp>288.15 K</temp></sample>
  </divecomputer>
</dive>
<dive number='2'>
  <divecomputer model='Suunto Vyper'><sample time='0:10 min' depth='3 m' /></divecomputer>
</dive>
<dive number='3' date='2.4.2014' time='9:5'>
  <sample time='30' depth='4 m' />
  <sample time='1:00:00' depth='5 m' />
</dive>
<dive number='4' date='2014-04-03' time='08:00:00' />
</dives></divelog>
"""


def test_subsurface_spellings_and_skipped_dives(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "log.xml"
    path.write_text(UNPADDED)
    first, third = read_logbook(path)
    assert first.start_iso == "2014-04-01T10:00:00" and first.fingerprint == "0A0B0C0D"
    offsets = (first.stamps_s - first.start_s).tolist()
    assert offsets == [10.0, 60.0, 120.0]  # the unreadable 'twelve' sample is skipped
    assert first.depth_m.tolist() == [3.5, 12.3, 10.0]  # decimal comma read as a point
    # -60 C is outside what a dive computer logs (Subsurface drops it too); K converted
    assert same(first.temperature_c[1], NAN) and first.temperature_c[2] == 15.0
    assert third.start_iso == "2014-04-02T09:05:00"  # d.m.y and h:m
    assert (third.stamps_s - third.start_s).tolist() == [30.0, 3600.0]
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert any("dive 1 divecomputer 1: 1 sample skipped" in w and "'twelve'" in w for w in warnings)
    assert any(w.endswith("dive 2 divecomputer 1: skipped (no date)") for w in warnings)
    assert any(w.endswith("dive 4: skipped (no samples)") for w in warnings)


# Subsurface's import of a Poseidon MkVI CSV log (its dives/Poseidon_MkVILog.xml): the
# 'subsurface-import' version 2 format, times without 'min', and the first seconds with
# an empty temperature (' C') and an empty oxygen pressure (' bar').
POSEIDON_IMPORT = """<divelog program="subsurface-import" version="2">
  <dives>
    <dive date="2011-06-14" time="11:20">
      <divecomputer model="Poseidon MkVI Discovery" deviceid='0567' dctype='CCR'>
        <sample time="0:00" depth="1 m" o2pressure=" bar" temp=" C" PO2="NaN bar"/>
        <sample time="0:02" depth="0.5 m" o2pressure=" bar" temp=" C" PO2="0.34 bar"/>
        <sample time="0:07" depth="0 m" o2pressure="183 bar" temp="26.6 C" PO2="0.37 bar"/>
        <sample time="1:5" depth=" m" temp="26.4 C"/>
      </divecomputer>
    </dive>
  </dives>
</divelog>
"""


def test_unreadable_temperature_keeps_its_sample(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "poseidon.xml"
    path.write_text(POSEIDON_IMPORT)
    (dive,) = read_logbook(path)
    assert dive.start_iso == "2011-06-14T11:20:00"
    # The samples with temp=' C' are kept without a temperature (Subsurface's
    # temperature() leaves it unset); the one whose depth cannot be read is skipped.
    assert (dive.stamps_s - dive.start_s).tolist() == [0.0, 2.0, 7.0]
    assert dive.depth_m.tolist() == [1.0, 0.5, 0.0]
    assert np.isnan(dive.temperature_c[:2]).all() and dive.temperature_c[2] == 26.6
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert any(
        "dive 1 divecomputer 1: 2 sample values unreadable, the samples kept without them "
        "(first: sample at 0:00: temperature:" in w
        for w in warnings
    ), warnings
    skipped = "dive 1 divecomputer 1: 1 sample skipped (first: sample at 1:5"
    assert any(skipped in w for w in warnings)


def test_unknown_temperature_unit_keeps_the_sample(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A temperature in a unit we do not know is left out, its sample kept (this file was
    refused whole before the Poseidon import showed that Subsurface keeps such samples)."""
    path = tmp_path / "badtemp.ssrf"
    path.write_text(
        "<divelog><dive date='2020-01-01'><sample time='1:00 min' depth='3 m' temp='3 X'/>"
        "</dive></divelog>"
    )
    (dive,) = read_logbook(path)
    assert dive.depth_m.tolist() == [3.0] and np.isnan(dive.temperature_c).all()
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert any("1 sample value unreadable" in w and "temperature unit 'x'" in w for w in warnings)


PLACEHOLDER_UDDF = """<?xml version="1.0" encoding="UTF-8"?>
<uddf version="3.3.0"><profiledata><repetitiongroup id="rg1">
<dive id="previous_dive"><informationbeforedive><surfaceintervalbeforedive><infinity/>
</surfaceintervalbeforedive></informationbeforedive></dive>
<dive id="dive"><informationbeforedive><datetime>2022-4-24 10:30:58</datetime>
</informationbeforedive><samples>
<waypoint><depth>0.0</depth><divetime>0.0</divetime><temperature>290.0</temperature></waypoint>
<waypoint><depth>2.2</depth><divetime>10.0</divetime><temperature>1e999</temperature></waypoint>
<waypoint><depth>x</depth><divetime>20.0</divetime></waypoint>
<waypoint><depth>4.6</depth><divetime>30.0</divetime></waypoint>
</samples></dive>
<dive id="old"><date><year>2011</year><month>5</month><day>17</day></date>
<time><hour>11</hour><minute>1</minute></time>
<samples><waypoint><depth>1.5</depth><divetime>30</divetime></waypoint></samples></dive>
</repetitiongroup></profiledata></uddf>
"""


def test_uddf_placeholder_dive_is_skipped(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / "apd.uddf"
    path.write_text(PLACEHOLDER_UDDF)
    dive, old = read_logbook(path)
    assert dive.start_iso == "2022-04-24T10:30:58" and dive.fingerprint == "dive"
    assert dive.depth_m.tolist() == [0.0, 2.2, 4.6]
    assert dive.temperature_c[0] == pytest.approx(16.85) and same(dive.temperature_c[1], NAN)
    assert old.start_iso == "2011-05-17T11:01:00" and old.depth_m.tolist() == [1.5]
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert any(
        w.endswith("dive previous_dive: skipped (no informationbeforedive/datetime)")
        for w in warnings
    )
    assert any("dive dive: 1 sample skipped (first: waypoint 3: 'x' is not" in w for w in warnings)


@pytest.mark.parametrize(
    ("text", "seconds"),
    [
        ("12:34 min", 754.0), ("1:02:03", 3723.0), ("754 s", 754.0), ("754", 754.0),
        ("30 min", 1800.0), ("0:10.5 min", 10.5), ("2.0", 2.0),
    ],
)  # fmt: skip
def test_sample_time_spellings(text: str, seconds: float) -> None:
    from field.divecomputer.importers.common import duration_s_from_text

    assert duration_s_from_text(text) == seconds


@pytest.mark.parametrize(
    ("date", "time", "iso"),
    [
        ("2014-4-1", "10:0:0", "2014-04-01T10:00:00"),
        ("2014-04-01", None, "2014-04-01T00:00:00"),
        ("1.4.2014", "7:30", "2014-04-01T07:30:00"),
        ("2011-03-20 10:22:38", None, "2011-03-20T10:22:38"),
        ("2014-04-02T10:00:00Z", None, "2014-04-02T10:00:00"),
        ("20140402T100000", None, "2014-04-02T10:00:00"),
    ],
)
def test_date_spellings(date: str, time: str | None, iso: str) -> None:
    from field.divecomputer.importers.common import combine_date_time

    assert combine_date_time(date, time) == iso


@pytest.mark.parametrize("date", ["2014-13-01", "2014-02-30", "0-1-1", "May 1", ""])
def test_impossible_dates_are_refused(date: str) -> None:
    from field.divecomputer.importers.common import combine_date_time

    with pytest.raises(ValueError, match="date"):
        combine_date_time(date, None)


def test_not_a_dive_log_names_the_element(tmp_path: Path) -> None:
    path = tmp_path / "suunto.xml"
    path.write_text(
        '<?xml version="1.0" encoding="ISO-8859-15" ?>\n<!-- exported -->\n'
        "<SUUNTO><HEADER><MSGNAME>SDM001A</MSGNAME></HEADER></SUUNTO>\n"
    )
    with pytest.raises(InputError, match=r"suunto\.xml: .*\(root element <SUUNTO>;") as caught:
        read_logbook(path)
    assert "\n" not in str(caught.value)


def folder_state(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def test_rejected_file_leaves_the_dive_folder_as_it_was(tmp_path: Path) -> None:
    good = tmp_path / "good.ssrf"
    good.write_text(SUBSURFACE_TRIP)
    out = tmp_path / "dives"
    assert len(import_logbook(good, out)) == 2
    before = folder_state(out)
    bad = tmp_path / "bad.ssrf"
    bad.write_text(
        "<divelog><dive number='9' date='2020-13-40'><sample time='1:00'/></dive></divelog>"
    )
    with pytest.raises(InputError, match=r"bad\.ssrf: no importable dive \(dive 9: no such date"):
        import_logbook(bad, out)
    broken = tmp_path / "broken.ssrf"
    broken.write_text(SUBSURFACE_TRIP.replace("</dive>", "</dove>"))
    with pytest.raises(InputError, match="malformed XML"):
        import_logbook(broken, out)
    assert folder_state(out) == before
    fresh = tmp_path / "fresh"
    with pytest.raises(InputError):
        import_logbook(bad, fresh)
    assert not fresh.exists()


def test_a_taken_csv_name_skips_that_dive_only(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    good = tmp_path / "good.ssrf"
    good.write_text(SUBSURFACE_TRIP)
    out = tmp_path / "dives"
    assert len(import_logbook(good, out)) == 2
    before = folder_state(out)
    # Same dives, other model: new dives by identity, but their CSV names are taken.
    other = tmp_path / "other.ssrf"
    other.write_text(SUBSURFACE_TRIP.replace("model='A'", "model='A2'"))
    assert import_logbook(other, out) == []
    assert folder_state(out) == before
    assert any("already taken by another dive" in r.getMessage() for r in caplog.records)


def test_csv_odd_line_is_skipped(shared_data: Path, tmp_path: Path) -> None:
    lines = (shared_data / "divelogs" / "shearwater-petrel3-dive88.csv").read_text().splitlines()
    damaged = tmp_path / "damaged.csv"
    damaged.write_text(
        "\n".join([*lines[:4], "10,deep" + lines[4][len(lines[4].split(",")[0]) + 4 :], *lines[5:]])
    )
    (dive,) = read_logbook(damaged)
    assert dive.stamps_s.size == len(lines) - 4


def test_dives_sharing_a_logbook_id_stay_apart(tmp_path: Path) -> None:
    dive = "<dive date='2020-05-0{day}' time='09:00'><divecomputer model='A' diveid='00000002'>"
    dive += "<sample time='1:00 min' depth='{depth} m'/></divecomputer></dive>"
    repeat = dive.format(day=1, depth=1)  # the same dive twice is one dive
    body = "".join(dive.format(day=d, depth=d) for d in (1, 2, 3)) + repeat
    path = tmp_path / "ids.ssrf"
    path.write_text(f"<divelog><dives>{body}</dives></divelog>")
    dives = read_logbook(path)
    assert len({d.fingerprint for d in dives}) == 3 and "00000002" not in {
        d.fingerprint for d in dives
    }
    assert len(import_logbook(path, tmp_path / "dives")) == 3


# libdivecomputer's XML dump, Subsurface's first input (its dives/2011-*.xml): top-level
# <dive> elements without a root, values as child elements, bare metres and degrees C.
LIBDIVECOMPUTER_DUMP = """<?xml version="1.0"?>
<!-- dumped by libdivecomputer -->
<dive>
<number>1</number>
<fingerprint>0E130FDB070710</fingerprint>
<datetime>2011-07-16 14:19:15</datetime>
<divetime>00:40</divetime>
<maxdepth>2.05</maxdepth>
<gasmix><he>0.0</he><o2>32.0</o2><n2>68.0</n2></gasmix>
<sample>
   <time>00:00</time>
   <depth>1.22</depth>
   <pressure tank="0">185.32</pressure>
   <temperature>16.00</temperature>
</sample>
<sample>
   <time>00:20</time>
   <depth>2.05</depth>
   <event type="3" time="14" flags="1" value="0">ascent</event>
</sample>
<sample>
   <time>00:40</time>
   <depth>1.79</depth>
</sample>
</dive>
<dive>
<number>2</number>
<datetime>2011-07-16 16:02:00</datetime>
<sample><time>00:00</time><depth>0.5</depth></sample>
<sample><time>01:00</time><depth>3.5</depth></sample>
</dive>
"""


def test_libdivecomputer_dump_every_dive(tmp_path: Path) -> None:
    path = tmp_path / "2011-07-16.xml"
    path.write_text(LIBDIVECOMPUTER_DUMP)
    assert detect_format(path) == "subsurface"
    first, second = read_logbook(path)
    assert (first.start_iso, second.start_iso) == ("2011-07-16T14:19:15", "2011-07-16T16:02:00")
    np.testing.assert_array_equal(first.stamps_s - first.stamps_s[0], [0.0, 20.0, 40.0])
    np.testing.assert_array_equal(first.depth_m, [1.22, 2.05, 1.79])
    assert first.temperature_c[0] == 16.0 and np.isnan(first.temperature_c[1:]).all()
    np.testing.assert_array_equal(second.depth_m, [0.5, 3.5])
    assert len(import_logbook(path, tmp_path / "dives")) == 2
    # One dive alone is a well-formed document with root <dive>; read the same way.
    single = tmp_path / "single.xml"
    single.write_text(LIBDIVECOMPUTER_DUMP.split("<dive>\n<number>2")[0])
    (alone,) = read_logbook(single)
    assert alone.start_iso == first.start_iso and alone.stamps_s.size == 3
    # A dump cut short is malformed XML, refused in one line naming the file.
    cut = tmp_path / "cut.xml"
    cut.write_text(LIBDIVECOMPUTER_DUMP[:300])
    with pytest.raises(InputError, match=r"cut\.xml:\d+:\d+: malformed XML") as caught:
        read_logbook(cut)
    assert "\n" not in str(caught.value)
