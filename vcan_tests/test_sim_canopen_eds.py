"""Tolerant EDS reading (``chcos.devices.eds_file``), field by field: every field of a vendor-style
EDS emptied in turn is either read (with a warning naming the file, section and key when it is a
number canopen needs) or refused with an error naming them - never a traceback, never an error
that leaves the user guessing which line."""

from __future__ import annotations

import configparser
import io
from pathlib import Path

import pytest

from chcos.devices.eds_file import DEVICE_INFO_TEXT, OBJECT_MAY_BE_EMPTY, clean, read_eds

AWKWARD = Path(__file__).resolve().parent / "vendor" / "awkward_ax7.eds"
#: every kind of section once: file and device information, a variable with and without a
#: default, records' headers and entries (identity, PDO parameters)
SAMPLED = {"FileInfo", "DeviceInfo", "DummyUsage", "Comments", "1000", "1017", "1018",
           "1018sub1", "1800", "1800sub0", "1800sub2", "1A00", "1A00sub1", "2000", "6040"}


def _fields(text: str) -> list[tuple[str, str]]:
    parser = configparser.RawConfigParser(inline_comment_prefixes=(";",), interpolation=None)
    parser.optionxform = str  # type: ignore[assignment,method-assign]
    parser.read_string(text)
    return [(s, k) for s in parser.sections() for k, v in parser.items(s) if v.strip()]


def _emptied(text: str, section: str, key: str) -> str:
    parser = configparser.RawConfigParser(inline_comment_prefixes=(";",), interpolation=None)
    parser.optionxform = str  # type: ignore[assignment,method-assign]
    parser.read_string(text)
    parser.set(section, key, "")
    out = io.StringIO()
    parser.write(out)
    return out.getvalue()


def test_every_field_emptied_is_read_or_refused_by_name(tmp_path: Path) -> None:
    text = AWKWARD.read_text(encoding="utf-8")
    fields = [(s, k) for s, k in _fields(text) if s in SAMPLED]
    assert len(fields) > 60
    eds = tmp_path / "probe.eds"
    refused = []
    for section, key in fields:
        eds.write_text(_emptied(text, section, key), encoding="utf-8")
        try:
            read = read_eds(eds, 3)
        except ValueError as exc:
            assert f"probe.eds: [{section}] {key}: empty" in str(exc), (section, key, exc)
            refused.append(key)
            continue
        warned = any(f"[{section}] {key}: empty value" in w for w in read.warnings)
        if section == "DeviceInfo":
            assert warned == (key not in DEVICE_INFO_TEXT), (section, key)
        if key in OBJECT_MAY_BE_EMPTY:
            assert not warned, (section, key)        # CiA 306 allows these empty
        if key == "ObjectType" and section in ("1800", "1A00"):
            assert warned and len(read.od[int(section, 16)]) > 1   # still a record
    assert set(refused) == {"DataType"}


def test_clean_leaves_a_complete_file_alone() -> None:
    text = AWKWARD.read_text(encoding="utf-8").replace("=\n", "=0\n")
    cleaned, warnings = clean(text, "x.eds")
    assert warnings == [] and "VendorNumber = 0" in cleaned


@pytest.mark.parametrize(("text", "match"), [
    ("[1000\nDataType=7\n", r"x\.eds: not an EDS \(INI\) file"),
    ("[1000]\nParameterName=a\nDataType=zz\nAccessType=ro\n", r"not a readable EDS"),
])
def test_what_cannot_be_read_is_an_error_naming_the_file(tmp_path: Path, text: str,
                                                         match: str) -> None:
    eds = tmp_path / "x.eds"
    eds.write_text(text, encoding="utf-8")
    with pytest.raises(ValueError, match=match):
        read_eds(eds, 1)
    with pytest.raises(ValueError, match=r"no\.eds: cannot read the EDS"):
        read_eds(tmp_path / "no.eds", 1)
