"""Recipes are refused before any bus traffic unless every value is present,
typed and in range, and every problem names the file and the dotted field."""

from __future__ import annotations

import copy
import hashlib
import json
import shutil
import tomllib
from dataclasses import replace
from importlib.resources import files
from pathlib import Path
from typing import Any

import pytest

from station.errors import ExitCode, InputError
from station.methods.coherent import CoherentSweep
from station.methods.paper import PaperSweep
from station.recipes import (
    DEFAULT_RECIPE,
    RECIPE_FORMAT,
    RecipeError,
    Verification,
    available_recipes,
    load_recipe,
    parse_recipe,
)

SOURCE = "trial.toml"


def shipped_path(name: str) -> Path:
    return Path(str(files("recipes") / f"{name}.toml"))


def shipped_data(name: str) -> dict[str, Any]:
    return tomllib.loads(shipped_path(name).read_text(encoding="utf-8"))


def _value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)  # a JSON string is a TOML basic string
    if isinstance(value, list):
        return "[" + ", ".join(_value(v) for v in value) + "]"
    raise TypeError(value)


def to_toml(data: dict[str, Any], prefix: str = "") -> str:
    """Just enough TOML writing for these tests (tomllib only reads)."""
    scalars = [f"{k} = {_value(v)}" for k, v in data.items() if not isinstance(v, dict)]
    text = "\n".join(scalars) + "\n"
    for key, table in data.items():
        if isinstance(table, dict):
            text += f"\n[{prefix}{key}]\n" + to_toml(table, f"{prefix}{key}.")
    return text


def problems(data: dict[str, Any]) -> tuple[str, ...]:
    """The problems a recipe is refused for; each line must name the file."""
    with pytest.raises(RecipeError) as caught:
        parse_recipe(to_toml(data), source=SOURCE)
    lines = str(caught.value).splitlines()
    assert lines == [f"{SOURCE}: {p}" for p in caught.value.problems]
    return caught.value.problems


def only_problem(data: dict[str, Any]) -> str:
    found = problems(data)
    assert len(found) == 1, found
    return found[0]


def paper() -> dict[str, Any]:
    return copy.deepcopy(shipped_data("paper"))


def coherent() -> dict[str, Any]:
    return copy.deepcopy(shipped_data("default"))


# --- the shipped recipes --------------------------------------------------------------


def test_both_shipped_recipes_are_available_and_default_is_one_of_them() -> None:
    assert available_recipes() == ["default", "paper"]
    assert DEFAULT_RECIPE in available_recipes()


def test_paper_recipe_follows_the_paper() -> None:
    recipe = load_recipe("paper")
    assert (recipe.name, recipe.version, recipe.method) == ("paper", "2", "paper")
    assert recipe.product.rated_current_mA == 1000
    assert (recipe.product.microsteps, recipe.product.rotor_teeth) == (256, 50)
    assert recipe.motion.electrical_hz == 20.0 and recipe.motion.amplitude_mA == 1000
    motion = recipe.motion
    assert (motion.spin_up_periods, motion.settle_periods, motion.dwell_periods) == (4, 4, 16)
    assert motion.sensor_range_g == 16
    # One second per point at 20 Hz, as the paper's sweeps are sampled.
    assert recipe.hold_periods() / recipe.motion.electrical_hz == 1.0
    assert recipe.sweep == PaperSweep(-500, 500, 11, 7000, 13000, 11)


def test_default_recipe_is_coherent_with_the_paper_s_product_and_limits() -> None:
    recipe = load_recipe(DEFAULT_RECIPE)
    reference = load_recipe("paper")
    assert recipe.method == "coherent"
    # Two more rounds at most for a unit whose σ is over its limit after three.
    assert recipe.sweep == CoherentSweep(offset_steps_mA=(100, 30, 10),
                                         gain_steps=(1000, 300, 100), sigma_rounds=2)
    assert (recipe.motion.dwell_periods, recipe.motion.sensor_range_g) == (4, 16)
    assert recipe.hold_periods() == 6
    # Short holds for the sweep; the verification settles briefly and goes on measuring
    # while a unit still rings (``max_dwell_periods``); a verification that fails on its
    # ripple alone corrects the trims once from its own phasors. The paper verifies once.
    assert recipe.verification == Verification(dwell_periods=4, settle_periods=2,
                                               max_dwell_periods=24, max_corrections=1)
    assert reference.verification == Verification(dwell_periods=20, settle_periods=None)
    assert reference.motion.settle_periods == 4
    assert recipe.product == reference.product
    assert recipe.self_check == reference.self_check
    assert recipe.limits == reference.limits


def test_shipped_limits_and_self_check_have_the_documented_values() -> None:
    recipe = load_recipe("paper")
    check, limits = recipe.self_check, recipe.limits
    assert (check.standstill_s, check.gravity_tolerance_mps2, check.max_noise_mps2) == (
        0.3,
        0.8,
        0.15,
    )
    assert recipe.verification.dwell_periods == 20
    assert (limits.max_h1_after_mps2, limits.max_h2_after_mps2) == (0.08, 0.25)
    assert (limits.min_reduction_db, limits.offset_bound_mA) == (6.0, 250.0)
    assert (limits.gain_min, limits.gain_max) == (8500, 11500)
    assert (limits.max_offset_sigma_mA, limits.max_gain_sigma, limits.min_fit_r_squared) == (
        3.0,
        30.0,
        0.99,
    )
    assert (limits.max_drift_offset_mA, limits.max_drift_gain) == (15.0, 100.0)


# --- the hash ------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["default", "paper"])
def test_hash_is_the_sha256_of_the_file_bytes(name: str) -> None:
    recipe = load_recipe(name)
    data = shipped_path(name).read_bytes()
    assert recipe.sha256 == hashlib.sha256(data).hexdigest()
    assert recipe.text.encode("utf-8") == data


def test_hash_changes_when_one_character_changes(tmp_path: Path) -> None:
    original = shipped_path("paper").read_text(encoding="utf-8")
    edited = original.replace("# The paper's", "# The paper’s", 1)
    assert edited != original
    path = tmp_path / "paper.toml"
    path.write_text(edited, encoding="utf-8")
    changed = load_recipe(path)
    assert changed.sha256 != load_recipe("paper").sha256
    assert changed.sweep == load_recipe("paper").sweep  # same values, different text


def test_hash_covers_the_file_s_own_line_endings(tmp_path: Path) -> None:
    path = tmp_path / "paper.toml"
    data = shipped_path("paper").read_bytes().replace(b"\n", b"\r\n")
    path.write_bytes(data)
    assert load_recipe(path).sha256 == hashlib.sha256(data).hexdigest()


# --- structure and types ---------------------------------------------------------------


def test_unknown_top_level_key_is_refused() -> None:
    data = paper()
    data["colour"] = "blue"
    assert only_problem(data) == "colour: unknown key"


def test_unknown_nested_key_is_named_by_its_dotted_path() -> None:
    data = paper()
    data["motion"]["dwell_period"] = 16
    assert only_problem(data) == "motion.dwell_period: unknown key (did you mean 'dwell_periods'?)"


def test_unknown_nested_table_is_refused() -> None:
    data = paper()
    data["limits"]["extra"] = {"x": 1}
    assert only_problem(data).startswith("limits.extra: unknown key")


def test_missing_key_is_refused_because_nothing_has_a_default() -> None:
    data = paper()
    del data["motion"]["settle_periods"]
    assert only_problem(data) == "motion.settle_periods: missing"


def test_missing_table_is_reported_once_not_key_by_key() -> None:
    data = paper()
    del data["self_check"]
    assert only_problem(data) == "self_check: missing"


def test_table_given_as_a_value_is_refused() -> None:
    data = paper()
    data["verification"] = 20
    assert only_problem(data) == "verification: expected a table, got an integer 20"


@pytest.mark.parametrize(
    ("table", "key"),
    [("motion", "electrical_hz"), ("motion", "dwell_periods"), ("limits", "min_fit_r_squared")],
)
def test_bool_is_never_a_number(table: str, key: str) -> None:
    data = paper()
    data[table][key] = True
    problem = only_problem(data)
    assert problem.startswith(f"{table}.{key}: expected ")
    assert problem.endswith("got a boolean True")


def test_float_is_refused_where_an_int_is_expected() -> None:
    data = paper()
    data["motion"]["dwell_periods"] = 16.0
    assert only_problem(data) == "motion.dwell_periods: expected an integer, got a float 16.0"


def test_int_is_accepted_where_a_float_is_expected() -> None:
    data = paper()
    data["motion"]["electrical_hz"] = 20
    data["limits"]["max_h1_after_mps2"] = 1
    recipe = parse_recipe(to_toml(data))
    assert recipe.motion.electrical_hz == 20.0
    assert isinstance(recipe.limits.max_h1_after_mps2, float)


def test_string_where_a_number_is_expected_is_refused() -> None:
    data = paper()
    data["product"]["rated_current_mA"] = "1000"
    assert only_problem(data) == (
        "product.rated_current_mA: expected an integer, got a string '1000'"
    )


def test_array_elements_must_be_integers() -> None:
    data = coherent()
    data["sweep"]["gain_steps"] = [1000, 300.5]
    assert only_problem(data) == "sweep.gain_steps[1]: expected an integer, got a float 300.5"


@pytest.mark.parametrize("text", ["nan", "inf", "-inf"])
def test_non_finite_floats_are_refused(text: str) -> None:
    source = shipped_path("paper").read_text(encoding="utf-8")
    assert "min_fit_r_squared = 0.99 " in source
    edited = source.replace("min_fit_r_squared = 0.99 ", f"min_fit_r_squared = {text} ")
    with pytest.raises(RecipeError) as caught:
        parse_recipe(edited, source=SOURCE)
    assert caught.value.problems == (f"limits.min_fit_r_squared: must be finite, got {text}",)


# --- ranges ----------------------------------------------------------------------------

RANGE_CASES: list[tuple[str, str, object]] = [
    ("product", "rated_current_mA", 0),
    ("product", "rated_current_mA", 65536),
    ("product", "microsteps", 0),
    ("product", "microsteps", 257),
    ("product", "rotor_teeth", 0),
    ("product", "rotor_teeth", 1001),
    ("motion", "electrical_hz", 0),
    ("motion", "electrical_hz", -1.0),
    ("motion", "electrical_hz", 50.5),
    ("motion", "amplitude_mA", 0),
    ("motion", "spin_up_periods", -1),
    ("motion", "spin_up_periods", 1001),
    ("motion", "settle_periods", -1),
    ("motion", "settle_periods", 1001),
    ("motion", "dwell_periods", 2),
    ("motion", "dwell_periods", 10001),
    ("motion", "sensor_range_g", 6),
    ("sweep", "offset_min_mA", -501),
    ("sweep", "offset_max_mA", 501),
    ("sweep", "offset_points", 2),
    ("sweep", "offset_points", 102),
    ("sweep", "gain_min", 4999),
    ("sweep", "gain_max", 15001),
    ("sweep", "gain_points", 2),
    ("sweep", "gain_points", 102),
    ("self_check", "standstill_s", 0),
    ("self_check", "standstill_s", 10.5),
    ("self_check", "gravity_tolerance_mps2", 0),
    ("self_check", "gravity_tolerance_mps2", 9.80665),
    ("self_check", "max_noise_mps2", 0),
    ("verification", "dwell_periods", 2),
    ("verification", "dwell_periods", 10001),
    ("verification", "max_dwell_periods", 2),
    ("verification", "max_dwell_periods", 10001),
    ("verification", "max_corrections", -1),
    ("verification", "max_corrections", 4),
    ("limits", "max_h1_after_mps2", 0),
    ("limits", "max_h2_after_mps2", -0.1),
    ("limits", "min_reduction_db", -1),
    ("limits", "offset_bound_mA", 0),
    ("limits", "offset_bound_mA", 500.5),
    ("limits", "gain_min", 4999),
    ("limits", "gain_max", 15001),
    ("limits", "max_offset_sigma_mA", 0),
    ("limits", "max_gain_sigma", 0),
    ("limits", "min_fit_r_squared", 0),
    ("limits", "min_fit_r_squared", 1),
    ("limits", "min_fit_r_squared", 1.0),
    ("limits", "min_fit_r_squared", -0.1),
    ("limits", "min_fit_r_squared", 1.5),
    ("limits", "max_drift_offset_mA", 0),
    ("limits", "max_drift_gain", 0),
    ("clipping", "max_share", -0.01),
    ("clipping", "max_share", 1.0),
    ("clipping", "step_shrink", 0),
    ("clipping", "step_shrink", 1.0),
    ("clipping", "retries", -1),
    ("clipping", "retries", 11),
]


@pytest.mark.parametrize(("table", "key", "value"), RANGE_CASES)
def test_value_out_of_range_is_refused_naming_the_field(
    table: str, key: str, value: object
) -> None:
    data = paper()
    data[table][key] = value
    problem = only_problem(data)
    assert problem.startswith(f"{table}.{key}: must be ")
    assert f"got {value!r}" in problem


def test_shipped_recipes_act_on_clipping_at_the_widest_sensor_range() -> None:
    for name in ("default", "paper"):
        recipe = load_recipe(name)
        assert recipe.motion.sensor_range_g == 16
        assert recipe.clipping is not None
        assert 0 < recipe.clipping.max_share < 0.5 and recipe.clipping.retries >= 1


def test_a_verification_without_its_own_settle_settles_as_a_sweep_hold_does() -> None:
    data = coherent()
    del data["verification"]["settle_periods"]
    assert parse_recipe(to_toml(data), source=SOURCE).verification.settle_periods is None
    data["verification"]["settle_periods"] = 1001
    assert only_problem(data).startswith("verification.settle_periods: must be ")


def test_a_verification_goes_on_measuring_only_where_its_recipe_says_how_long() -> None:
    data = coherent()
    data["verification"].pop("max_dwell_periods", None)
    # A recipe written before the key: the one hold, as it always was.
    assert parse_recipe(to_toml(data), source=SOURCE).verification.max_dwell_periods is None
    data["verification"]["max_dwell_periods"] = 40
    assert parse_recipe(to_toml(data), source=SOURCE).verification.max_dwell_periods == 40
    data["verification"]["max_dwell_periods"] = data["verification"]["dwell_periods"] - 1
    assert only_problem(data) == (
        "verification.max_dwell_periods: must be >= verification.dwell_periods "
        f"({data['verification']['dwell_periods']}): the first hold alone measures that "
        f"long, got {data['verification']['dwell_periods'] - 1}")


def test_a_verification_corrects_the_trims_only_where_its_recipe_allows() -> None:
    data = coherent()
    data["verification"].pop("max_corrections", None)
    # A recipe written before the key verifies once and judges that.
    assert parse_recipe(to_toml(data), source=SOURCE).verification.max_corrections == 0
    data["verification"]["max_corrections"] = 2
    assert parse_recipe(to_toml(data), source=SOURCE).verification.max_corrections == 2
    data["verification"]["max_corrections"] = True
    assert only_problem(data).startswith("verification.max_corrections: ")


def test_a_magnitude_sweep_may_hold_its_points_longer_than_the_star_does() -> None:
    recipe = parse_recipe(to_toml(coherent()), source=SOURCE)
    assert recipe.magnitude_sweep is not None
    sweep = recipe.magnitude_sweep
    # A Modbus write's uncertain samples cost about a period of every hold.
    assert sweep.settle_periods is not None and sweep.dwell_periods is not None
    assert sweep.settle_periods + sweep.dwell_periods > recipe.hold_periods()
    data = coherent()
    del data["magnitude_sweep"]["settle_periods"], data["magnitude_sweep"]["dwell_periods"]
    older = parse_recipe(to_toml(data), source=SOURCE).magnitude_sweep
    assert older is not None and (older.settle_periods, older.dwell_periods) == (None, None)
    data["magnitude_sweep"]["dwell_periods"] = 2
    data["magnitude_sweep"]["settle_periods"] = -1
    found = problems(data)
    assert len(found) == 2
    assert any(p.startswith("magnitude_sweep.dwell_periods: must be ") for p in found)
    assert any(p.startswith("magnitude_sweep.settle_periods: must be ") for p in found)


def test_a_recipe_without_a_clipping_table_only_says_what_clipped() -> None:
    # Recipes written before the table existed still parse, and mean what they did then.
    data = coherent()
    del data["clipping"]
    assert parse_recipe(to_toml(data), source=SOURCE).clipping is None


def test_a_clipping_table_must_be_complete_and_holds_no_other_key() -> None:
    data = coherent()
    del data["clipping"]["retries"]
    data["clipping"]["range_g"] = 8
    assert set(problems(data)) == {"clipping.retries: missing",
                                   "clipping.range_g: unknown key"}


@pytest.mark.parametrize("value", [0, 1, 1.0, -0.1, 1.5])
def test_the_fit_r_squared_minimum_must_lie_strictly_between_0_and_1(value: object) -> None:
    data = paper()
    data["limits"]["min_fit_r_squared"] = value
    assert only_problem(data) == f"limits.min_fit_r_squared: must be in (0, 1), got {value!r}"


def test_a_recipe_with_the_old_chi2_limit_is_refused() -> None:
    data = paper()
    del data["limits"]["min_fit_r_squared"]
    data["limits"]["max_fit_chi2"] = 25.0
    with pytest.raises(RecipeError) as caught:
        parse_recipe(to_toml(data), source=SOURCE)
    missing, unknown = caught.value.problems
    assert missing == "limits.min_fit_r_squared: missing"
    assert unknown.startswith("limits.max_fit_chi2: unknown key")


@pytest.mark.parametrize(
    ("table", "key", "value"),
    [
        ("motion", "electrical_hz", 50),
        ("motion", "spin_up_periods", 0),
        ("motion", "settle_periods", 0),
        ("motion", "dwell_periods", 3),
        ("sweep", "offset_min_mA", -1),
        ("sweep", "offset_points", 3),
        ("sweep", "gain_points", 101),
        ("self_check", "standstill_s", 10),
        ("limits", "min_reduction_db", 0),
        ("limits", "offset_bound_mA", 500),
        ("limits", "gain_min", 10000),
        ("limits", "min_fit_r_squared", 0.001),
        ("limits", "min_fit_r_squared", 0.9999),
    ],
)
def test_values_at_the_edges_of_their_ranges_are_accepted(
    table: str, key: str, value: object
) -> None:
    data = paper()
    data[table][key] = value
    assert getattr(getattr(parse_recipe(to_toml(data)), table), key) == value


@pytest.mark.parametrize(
    ("key", "value", "expected"),
    [
        ("offset_steps_mA", [], "sweep.offset_steps_mA: must not be empty"),
        ("offset_steps_mA", [0, 30], "sweep.offset_steps_mA[0]: must be in 1..500"),
        ("offset_steps_mA", [100, 501], "sweep.offset_steps_mA[1]: must be in 1..500"),
        ("gain_steps", [5001, 300], "sweep.gain_steps[0]: must be in 1..5000"),
        ("gain_steps", [1000, -1], "sweep.gain_steps[1]: must be in 1..5000"),
        ("gain_steps", 1000, "sweep.gain_steps: expected an array of integers"),
    ],
)
def test_coherent_steps_out_of_range_are_refused(key: str, value: object, expected: str) -> None:
    data = coherent()
    data["sweep"][key] = value
    found = problems(data)
    assert any(p.startswith(expected) for p in found), found


def test_coherent_sweep_has_at_most_five_rounds() -> None:
    data = coherent()
    data["sweep"]["offset_steps_mA"] = [100, 80, 60, 40, 20, 10]
    data["sweep"]["gain_steps"] = [1000, 800, 600, 400, 200, 100]
    assert problems(data) == (
        "sweep.offset_steps_mA: must have at most 5 rounds, got 6",
        "sweep.gain_steps: must have at most 5 rounds, got 6",
    )


@pytest.mark.parametrize(
    ("key", "value", "expected"),
    [
        ("format", "station-recipe/2", "format: must be 'station-recipe/1'"),
        ("name", "Paper", "name: 'Paper' does not match"),
        ("name", "-paper", "name: '-paper' does not match"),
        ("version", "", "version: '' does not match"),
        ("version", "v1", "version: 'v1' does not match"),
        ("version", "1.", "version: '1.' does not match"),
        ("version", 1, "version: expected a string, got an integer 1"),
        ("method", "newton", "method: must be one of 'paper', 'coherent'"),
        ("description", None, "description: missing"),
    ],
)
def test_top_level_values_are_checked(key: str, value: object, expected: str) -> None:
    data = paper()
    if value is None:
        del data[key]
    else:
        data[key] = value
    assert only_problem(data).startswith(expected)


def test_product_name_must_not_be_empty() -> None:
    data = paper()
    data["product"]["name"] = ""
    assert only_problem(data) == "product.name: must not be empty"


def test_versions_with_several_parts_and_empty_descriptions_are_accepted() -> None:
    data = paper()
    data["version"], data["description"] = "1.2.0", ""
    recipe = parse_recipe(to_toml(data))
    assert (recipe.version, recipe.description) == ("1.2.0", "")


# --- cross-field rules -----------------------------------------------------------------


def test_amplitude_above_the_rated_current_is_refused() -> None:
    data = paper()
    data["motion"]["amplitude_mA"] = 1001
    assert only_problem(data) == (
        "motion.amplitude_mA: must be in 1..1000, got 1001 (at most product.rated_current_mA)"
    )


def test_offset_ranges_follow_the_rated_current() -> None:
    data = paper()
    data["product"]["rated_current_mA"] = 800
    data["motion"]["amplitude_mA"] = 800
    data["limits"]["offset_bound_mA"] = 400.5
    assert problems(data) == (
        "sweep.offset_min_mA: must be in -400..400, got -500 "
        "(the drive's offset range: half of product.rated_current_mA)",
        "sweep.offset_max_mA: must be in -400..400, got 500 "
        "(the drive's offset range: half of product.rated_current_mA)",
        "limits.offset_bound_mA: must be in (0, 400], got 400.5 "
        "(at most half of product.rated_current_mA, the drive's offset range)",
    )


def test_invalid_rated_current_does_not_cascade_into_other_fields() -> None:
    data = paper()
    data["product"]["rated_current_mA"] = -5
    assert only_problem(data).startswith("product.rated_current_mA:")


@pytest.mark.parametrize(
    ("low", "high", "expected"),
    [
        (100, 500, "sweep.offset_min_mA: must be <= 0: the range 100..500 must contain 0"),
        (-500, -100, "sweep.offset_max_mA: must be >= 0: the range -500..-100 must contain 0"),
        (200, -200, "sweep.offset_min_mA: must be less than sweep.offset_max_mA (-200), got 200"),
        (0, 0, "sweep.offset_min_mA: must be less than sweep.offset_max_mA (0), got 0"),
    ],
)
def test_paper_offset_sweep_must_be_ordered_and_pass_through_zero(
    low: int, high: int, expected: str
) -> None:
    data = paper()
    data["sweep"]["offset_min_mA"], data["sweep"]["offset_max_mA"] = low, high
    assert only_problem(data) == expected


@pytest.mark.parametrize("table", ["sweep", "limits"])
@pytest.mark.parametrize(
    ("low", "high", "field"),
    [(10500, 13000, "gain_min"), (7000, 9500, "gain_max"), (12000, 8000, "gain_min")],
)
def test_gain_ranges_must_be_ordered_and_contain_unity(
    table: str, low: int, high: int, field: str
) -> None:
    data = paper()
    data[table]["gain_min"], data[table]["gain_max"] = low, high
    assert only_problem(data).startswith(f"{table}.{field}: must be ")


def test_coherent_arrays_of_unequal_length_are_refused() -> None:
    data = coherent()
    data["sweep"]["gain_steps"] = [1000, 300]
    assert only_problem(data) == (
        "sweep.gain_steps: must have as many rounds as sweep.offset_steps_mA (3), got 2"
    )


def test_sweep_key_of_the_other_method_is_reported_as_not_used() -> None:
    data = paper()
    data["sweep"]["gain_steps"] = [1000]
    assert only_problem(data) == "sweep.gain_steps: not used by the paper method"
    data = coherent()
    data["sweep"]["offset_points"] = 11
    assert only_problem(data) == "sweep.offset_points: not used by the coherent method"


def test_paper_sweep_keys_are_missing_when_the_method_is_paper() -> None:
    data = coherent()
    data["method"] = "paper"
    found = problems(data)
    assert "sweep.offset_min_mA: missing" in found
    assert "sweep.offset_steps_mA: not used by the paper method" in found


def test_an_invalid_method_leaves_the_sweep_unjudged() -> None:
    data = paper()
    data["method"] = "guess"
    data["sweep"]["anything"] = 1
    assert only_problem(data).startswith("method: must be one of")


# --- names, files and reporting ----------------------------------------------------------


def test_name_must_equal_the_file_stem(tmp_path: Path) -> None:
    path = tmp_path / "nema17.toml"
    shutil.copy(shipped_path("paper"), path)
    with pytest.raises(RecipeError) as caught:
        load_recipe(path)
    assert str(caught.value) == f"{path}: name: 'paper' must equal the file's name 'nema17'"


def test_parse_checks_the_expected_name_only_when_given() -> None:
    text = shipped_path("paper").read_text(encoding="utf-8")
    assert parse_recipe(text).source == "<text>"
    with pytest.raises(RecipeError, match="name: 'paper' must equal the file's name 'other'"):
        parse_recipe(text, expected_name="other")


def test_bad_toml_syntax_names_the_file_and_line(tmp_path: Path) -> None:
    path = tmp_path / "broken.toml"
    path.write_text('format = "station-recipe/1"\nname = \n', encoding="utf-8")
    with pytest.raises(RecipeError) as caught:
        load_recipe(path)
    message = str(caught.value)
    assert message.startswith(f"{path}: line 2, column 8: invalid TOML: ")
    assert len(message.splitlines()) == 1


def test_several_problems_are_reported_together_one_per_line() -> None:
    data = paper()
    data["motion"]["dwell_periods"] = 1
    data["limits"]["min_fit_r_squared"] = False
    data["sweep"]["colour"] = "red"
    del data["product"]["rotor_teeth"]
    with pytest.raises(RecipeError) as caught:
        parse_recipe(to_toml(data), source=SOURCE)
    assert str(caught.value).splitlines() == [
        f"{SOURCE}: product.rotor_teeth: missing",
        f"{SOURCE}: motion.dwell_periods: must be in 3..10000, got 1",
        f"{SOURCE}: sweep.colour: unknown key",
        f"{SOURCE}: limits.min_fit_r_squared: expected a number, got a boolean False",
    ]


def test_recipe_errors_are_input_errors_with_exit_code_2() -> None:
    with pytest.raises(InputError) as caught:
        parse_recipe("")
    assert isinstance(caught.value, RecipeError)
    assert caught.value.exit_code is ExitCode.USAGE
    assert "format: missing" in caught.value.problems


def test_load_by_path_and_by_name_give_the_same_recipe(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    by_name = load_recipe("paper")
    copied = tmp_path / "paper.toml"
    shutil.copy(shipped_path("paper"), copied)
    for how in (copied, str(copied)):
        by_path = load_recipe(how)
        assert by_path.source == str(copied)
        assert by_path == replace(by_name, source=str(copied))
    monkeypatch.chdir(tmp_path)
    assert load_recipe("paper.toml").source == "paper.toml"


def test_a_bare_name_never_reads_the_working_directory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "paper.toml").write_text("not a recipe", encoding="utf-8")
    monkeypatch.chdir(tmp_path)
    assert (
        load_recipe("paper").sha256
        == hashlib.sha256(shipped_path("paper").read_bytes()).hexdigest()
    )


def test_unknown_name_lists_the_available_recipes() -> None:
    with pytest.raises(RecipeError) as caught:
        load_recipe("nema23")
    assert str(caught.value) == "nema23: no such recipe; available: default, paper"


def test_missing_file_is_a_recipe_error_naming_it(tmp_path: Path) -> None:
    path = tmp_path / "absent.toml"
    with pytest.raises(RecipeError, match=r"absent\.toml: cannot read"):
        load_recipe(path)


def test_file_that_is_not_utf8_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "paper.toml"
    path.write_bytes(shipped_path("paper").read_bytes().replace("°".encode(), b"\xb0"))
    with pytest.raises(RecipeError, match="not UTF-8 text"):
        load_recipe(path)


def test_recipe_format_constant_is_what_shipped_recipes_declare() -> None:
    assert all(shipped_data(name)["format"] == RECIPE_FORMAT for name in available_recipes())


def test_rounds_for_sigma_are_added_only_where_the_recipe_allows() -> None:
    data = coherent()
    data["sweep"].pop("sigma_rounds", None)
    # A recipe written before the key measures its own rounds and no more.
    assert parse_recipe(to_toml(data), source=SOURCE).sweep == CoherentSweep(
        tuple(data["sweep"]["offset_steps_mA"]), tuple(data["sweep"]["gain_steps"]))
    data["sweep"]["sigma_rounds"] = 3
    sweep = parse_recipe(to_toml(data), source=SOURCE).sweep
    assert isinstance(sweep, CoherentSweep) and sweep.sigma_rounds == 3
    for wrong in (-1, 4, 1.5):
        data["sweep"]["sigma_rounds"] = wrong
        assert only_problem(data).startswith("sweep.sigma_rounds: ")
    data = paper()
    data["sweep"]["sigma_rounds"] = 1  # the paper's sweeps have no rounds to add to
    assert only_problem(data).startswith("sweep.sigma_rounds: ")
