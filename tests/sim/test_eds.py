"""The EDS files against ICD.md's tables, written out here by hand from the ICD."""

from __future__ import annotations

import configparser
import re

import canopen
import pytest
from canopen.objectdictionary import ODVariable, datatypes

from drivers.eds import PERSISTED, DeviceKind, eds_path, load_od

U8, U16, U32 = datatypes.UNSIGNED8, datatypes.UNSIGNED16, datatypes.UNSIGNED32
I8, I16, I32 = datatypes.INTEGER8, datatypes.INTEGER16, datatypes.INTEGER32
REAL32 = datatypes.REAL32
NODE = 5  # not a default node-ID, so that $NODEID is seen to be resolved

# (index, subindex): (type, access, default or None when the ICD gives none)
DRIVE_OBJECTS: dict[tuple[int, int], tuple[int, str, int | None]] = {
    (0x1000, 0): (U32, "ro", 0x00030192),
    (0x1005, 0): (U32, "ro", 0x80),
    (0x1006, 0): (U32, "rw", 1000),
    (0x1010, 1): (U32, "rw", 1),
    (0x1011, 1): (U32, "rw", 1),
    (0x1017, 0): (U16, "rw", 100),
    (0x1018, 1): (U32, "ro", None),
    (0x1018, 2): (U32, "ro", None),
    (0x1018, 3): (U32, "ro", None),
    (0x1018, 4): (U32, "ro", None),
    (0x1019, 0): (U8, "rw", 240),
    (0x1800, 1): (U32, "rw", 0x180 + NODE),
    (0x1800, 2): (U8, "ro", 1),
    (0x1801, 1): (U32, "rw", 0x280 + NODE),
    (0x1801, 2): (U8, "ro", 1),
    (0x2100, 1): (I16, "rw", 0),
    (0x2100, 2): (I16, "rw", 0),
    (0x2100, 3): (U16, "rw", 10000),
    (0x2100, 4): (U16, "rw", 10000),
    (0x2101, 1): (U32, "rw", 0),
    (0x2101, 2): (U16, "rw", 0),
    (0x2101, 3): (U16, "rw", 0),
    (0x2102, 0): (U16, "rw", 256),
    (0x2103, 0): (U16, "rw", None),
    (0x6040, 0): (U16, "rw", None),
    (0x6041, 0): (U16, "ro", None),
    (0x6060, 0): (I8, "rw", 3),
    (0x6061, 0): (I8, "ro", 3),
    (0x6062, 0): (I32, "ro", None),
    (0x606B, 0): (I32, "ro", None),
    (0x6075, 0): (U32, "rw", None),
    (0x6083, 0): (U32, "rw", None),
    (0x6084, 0): (U32, "rw", None),
    (0x60FF, 0): (I32, "rw", 0),
}

SENSOR_OBJECTS: dict[tuple[int, int], tuple[int, str, int | None]] = {
    (0x1000, 0): (U32, "ro", None),
    (0x1017, 0): (U16, "rw", 100),
    (0x1018, 1): (U32, "ro", None),
    (0x1018, 2): (U32, "ro", None),
    (0x1018, 3): (U32, "ro", None),
    (0x1018, 4): (U32, "ro", None),
    (0x1800, 1): (U32, "rw", 0x180 + NODE),
    (0x1800, 2): (U8, "ro", 1),
    (0x2000, 0): (U8, "rw", 2),
    (0x2001, 0): (REAL32, "ro", None),
    (0x2010, 0): (U16, "ro", 0),
    (0x2020, 1): (I16, "ro", None),
    (0x2020, 2): (I16, "ro", None),
    (0x2020, 3): (I16, "ro", None),
}

# ICD.md PDO tables: mapped objects in order, with their sizes in bits.
DRIVE_TPDOS = {
    0: [(0x6062, 0, 32), (0x2103, 0, 16), (0x6041, 0, 16)],
    1: [(0x2100, 1, 16), (0x2100, 2, 16), (0x2100, 3, 16), (0x2100, 4, 16)],
}
SENSOR_TPDOS = {0: [(0x2010, 0, 16), (0x2020, 1, 16), (0x2020, 2, 16), (0x2020, 3, 16)]}

DRIVE_PERSISTED = {
    (0x2100, 1), (0x2100, 2), (0x2100, 3), (0x2100, 4),
    (0x2101, 1), (0x2101, 2), (0x2101, 3), (0x2102, 0), (0x6075, 0),
}  # fmt: skip


def _var(od: canopen.ObjectDictionary, index: int, subindex: int) -> ODVariable:
    obj = od[index]
    var = obj if isinstance(obj, ODVariable) else obj[subindex]
    assert isinstance(var, ODVariable)
    return var


def _all_variables(od: canopen.ObjectDictionary) -> list[ODVariable]:
    out: list[ODVariable] = []
    for obj in od.values():
        out.extend([obj] if isinstance(obj, ODVariable) else obj.values())
    return out


@pytest.mark.parametrize(
    ("kind", "table"), [(DeviceKind.DRIVE, DRIVE_OBJECTS), (DeviceKind.SENSOR, SENSOR_OBJECTS)]
)
def test_every_icd_object_has_the_icd_type_access_and_default(
    kind: DeviceKind, table: dict[tuple[int, int], tuple[int, str, int | None]]
) -> None:
    od = load_od(kind, NODE)
    for (index, subindex), (data_type, access, default) in table.items():
        var = _var(od, index, subindex)
        where = f"{kind} 0x{index:04X}:{subindex:02X}"
        assert var.data_type == data_type, where
        assert var.access_type == access, where
        if default is not None:
            assert var.default == default, where


def test_drive_gain_limits_are_the_icd_range() -> None:
    od = load_od(DeviceKind.DRIVE, NODE)
    for sub in (3, 4):
        var = _var(od, 0x2100, sub)
        assert (var.min, var.max) == (5000, 15000)


def test_sensor_sensitivity_default_is_two_g_over_full_scale() -> None:
    var = _var(load_od(DeviceKind.SENSOR, NODE), 0x2001, 0)
    assert var.default == pytest.approx(2 * 9.80665 / 32768, rel=1e-9)


def test_identity_in_the_object_dictionary_matches_device_info() -> None:
    for kind in DeviceKind:
        od = load_od(kind, NODE)
        info = od.device_information
        assert _var(od, 0x1018, 1).default == info.vendor_number
        assert _var(od, 0x1018, 2).default == info.product_number
        assert _var(od, 0x1018, 3).default == info.revision_number


@pytest.mark.parametrize(
    ("kind", "tpdos"), [(DeviceKind.DRIVE, DRIVE_TPDOS), (DeviceKind.SENSOR, SENSOR_TPDOS)]
)
def test_tpdo_mappings_are_the_icd_tables_in_order(
    kind: DeviceKind, tpdos: dict[int, list[tuple[int, int, int]]]
) -> None:
    od = load_od(kind, NODE)
    for number, expected in tpdos.items():
        mapping = od[0x1A00 + number]
        count = _var(od, 0x1A00 + number, 0).default
        entries = [_var(od, 0x1A00 + number, sub).default for sub in range(1, (count or 0) + 1)]
        assert entries == [(i << 16) | (s << 8) | bits for i, s, bits in expected], mapping.name
        total = 0
        for index, subindex, bits in expected:
            var = _var(od, index, subindex)
            assert var.pdo_mappable
            assert len(var) == bits
            total += bits
        assert total == 64  # ICD: every TPDO is 8 bytes
    # Nothing mapped beyond the ICD's PDOs.
    assert 0x1A00 + len(tpdos) not in od
    assert 0x1800 + len(tpdos) not in od


def test_drive_persisted_objects_are_exactly_those_the_icd_persists() -> None:
    od = load_od(DeviceKind.DRIVE, NODE)
    persisted = {
        (v.index, v.subindex) for v in _all_variables(od) if v.storage_location == PERSISTED
    }
    assert persisted == DRIVE_PERSISTED


def test_nodeid_relative_cob_ids_follow_the_node() -> None:
    for node in (1, 16, 127):
        od = load_od(DeviceKind.DRIVE, node)
        assert _var(od, 0x1800, 1).default == 0x180 + node
        assert _var(od, 0x1801, 1).default == 0x280 + node


def test_load_od_refuses_node_ids_outside_cia301() -> None:
    with pytest.raises(ValueError, match=r"1\.\.127"):
        load_od(DeviceKind.DRIVE, 0)
    with pytest.raises(ValueError, match=r"1\.\.127"):
        load_od(DeviceKind.SENSOR, 128)


# --- CiA 306 file structure, checked on the raw text ---------------------------------------

_OBJECT_SECTION = re.compile(r"[0-9A-F]{4}")
_SUB_SECTION = re.compile(r"([0-9A-F]{4})sub([0-9A-F]+)")
_VARIABLE_KEYS = {"ParameterName", "ObjectType", "DataType", "AccessType", "DefaultValue",
                  "PDOMapping"}  # fmt: skip


def _raw(kind: DeviceKind) -> configparser.RawConfigParser:
    parser = configparser.RawConfigParser(inline_comment_prefixes=(";",))
    parser.optionxform = str  # type: ignore[assignment,method-assign]
    parser.read(eds_path(kind), encoding="ascii")
    return parser


@pytest.mark.parametrize("kind", list(DeviceKind))
def test_eds_has_the_cia306_general_sections(kind: DeviceKind) -> None:
    eds = _raw(kind)
    for section in ("FileInfo", "DeviceInfo", "DummyUsage", "Comments", "MandatoryObjects",
                    "OptionalObjects", "ManufacturerObjects"):  # fmt: skip
        assert eds.has_section(section), section
    assert eds.get("FileInfo", "EDSVersion") == "4.0"
    assert eds.get("FileInfo", "FileName") == eds_path(kind).name
    lines = int(eds.get("Comments", "Lines"))
    assert all(eds.has_option("Comments", f"Line{n}") for n in range(1, lines + 1))
    assert [f"Dummy000{n}" for n in range(1, 8)] == list(eds["DummyUsage"])


@pytest.mark.parametrize("kind", list(DeviceKind))
def test_eds_object_lists_name_exactly_the_object_sections(kind: DeviceKind) -> None:
    eds = _raw(kind)
    listed: list[int] = []
    for group in ("MandatoryObjects", "OptionalObjects", "ManufacturerObjects"):
        count = int(eds.get(group, "SupportedObjects"))
        entries = [int(eds.get(group, str(n)), 16) for n in range(1, count + 1)]
        assert len(eds[group]) == count + 1, group
        listed += entries
        if group == "ManufacturerObjects":
            assert all(0x2000 <= e <= 0x5FFF for e in entries)
        else:
            assert not any(0x2000 <= e <= 0x5FFF for e in entries)
    sections = [int(s, 16) for s in eds.sections() if _OBJECT_SECTION.fullmatch(s)]
    assert sorted(listed) == sorted(sections)
    assert {0x1000, 0x1001, 0x1018} <= set(listed)


@pytest.mark.parametrize("kind", list(DeviceKind))
def test_eds_sections_carry_the_cia306_keys(kind: DeviceKind) -> None:
    eds = _raw(kind)
    subs: dict[int, list[int]] = {}
    for section in eds.sections():
        if match := _SUB_SECTION.fullmatch(section):
            subs.setdefault(int(match.group(1), 16), []).append(int(match.group(2), 16))
            assert set(eds[section]) >= _VARIABLE_KEYS, section
    for section in eds.sections():
        if not _OBJECT_SECTION.fullmatch(section):
            continue
        index = int(section, 16)
        object_type = int(eds.get(section, "ObjectType"), 0)
        if object_type == 0x7:
            assert set(eds[section]) >= _VARIABLE_KEYS, section
            assert index not in subs
        else:
            assert object_type in (0x8, 0x9), section
            assert int(eds.get(section, "SubNumber"), 0) == len(subs[index]), section
            assert 0 in subs[index]
            highest = int(eds.get(f"{section}sub0", "DefaultValue"), 0)
            assert highest == max(subs[index]), section


def test_device_info_counts_the_tpdos() -> None:
    assert _raw(DeviceKind.DRIVE).get("DeviceInfo", "NrOfTXPDO") == "2"
    assert _raw(DeviceKind.SENSOR).get("DeviceInfo", "NrOfTXPDO") == "1"

