"""The one unknown-key check (``v2xpos.schema``): what every config and descriptor reader says
about a misspelt key, an unknown choice, a value of the wrong type or outside its range."""
from __future__ import annotations

import pytest

from v2xpos.schema import Key, check_choice, check_keys, read_table


class TableError(ValueError):
    """Stands for a reader's own error class."""


def test_an_unknown_key_is_named_with_where_a_near_miss_and_the_allowed_keys():
    with pytest.raises(TableError) as e:
        check_keys({"lever_arm": 1, "file": "x"}, ("file", "lever_arm_m"), "d.toml: [gnss]", TableError)
    assert str(e.value) == ("d.toml: [gnss]: unknown key 'lever_arm' (did you mean 'lever_arm_m'?); "
                            "allowed ['file', 'lever_arm_m']")


def test_every_unknown_key_is_named_and_an_unordered_allowed_set_is_listed_sorted():
    with pytest.raises(ValueError) as e:
        check_keys({"fleeet": 1, "zzz": 2}, {"vehicle", "fleet"}, "x.toml: [service]")
    assert str(e.value) == ("x.toml: [service]: unknown keys 'fleeet' (did you mean 'fleet'?), 'zzz'; "
                            "allowed ['fleet', 'vehicle']")


def test_known_keys_pass():
    check_keys({"a": 1}, ("a", "b"), "w")


def test_an_unknown_choice_names_the_choices_and_the_near_miss():
    with pytest.raises(TableError, match=r"^s.format: 'ubxx' is not one of \['ubx', 'nmea'\] \(did you mean 'ubx'\?\)$"):
        check_choice("ubxx", ("ubx", "nmea"), "s.format", TableError)
    check_choice("ubx", ("ubx", "nmea"), "s.format")


SCHEMA = (Key("dataset", str), Key("speed_x", float, 1.0, above=0.0, high=10.0), Key("sync", bool, False),
          Key("count", int, 3, low=0))


def test_read_table_fills_defaults_and_accepts_integers_for_floats():
    assert read_table({"dataset": "d", "speed_x": 2}, SCHEMA, "w") == {
        "dataset": "d", "speed_x": 2.0, "sync": False, "count": 3}


@pytest.mark.parametrize("table, message", [
    ({}, "w.dataset: missing"),
    ({"dataset": "d", "speed_x": 0}, r"w.speed_x: expected a number in \(0.0, 10.0\], got 0.0"),
    ({"dataset": "d", "speed_x": 11.0}, r"w.speed_x: expected a number in \(0.0, 10.0\], got 11.0"),
    ({"dataset": "d", "speed_x": float("nan")}, "w.speed_x: expected a finite number"),
    ({"dataset": "d", "speed_x": True}, "w.speed_x: expected float, got bool True"),
    ({"dataset": "d", "sync": 1}, "w.sync: expected bool, got int 1"),
    ({"dataset": "d", "count": -1}, r"w.count: expected a number in \[0, inf\), got -1"),
    ({"dataset": "d", "sped_x": 1.0}, r"w: unknown key 'sped_x' \(did you mean 'speed_x'\?\)"),
    ([1], "w: expected a table, got list"),
])
def test_read_table_rejects_with_where_and_key(table, message):
    with pytest.raises(TableError, match=message):
        read_table(table, SCHEMA, "w", TableError)
