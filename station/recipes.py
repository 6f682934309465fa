"""Calibration recipes: how the station calibrates one product.

A recipe is a versioned TOML file, and the station refuses it before any bus
traffic unless every value is present, of the right type and within range. No
key has a default: what a run did must follow from the recipe text alone, so
that the SHA-256 each run stores identifies the procedure exactly. Problems are
collected and reported together, each line naming the file and the dotted
field, because whoever edits a recipe should fix it in one pass rather than one
error per attempt.
"""

from __future__ import annotations

import hashlib
import os
import re
import tomllib
from collections.abc import Sequence
from dataclasses import dataclass, fields
from importlib.resources import files
from pathlib import Path
from typing import Any, Final

from station.core import (
    GAIN_LIMITS,
    GAIN_UNITY,
    SENSOR_RANGES_G,
    STANDARD_GRAVITY,
)
from station.errors import InputError
from station.methods.tables import span
from station.tomltable import TomlTable, toml_error

RECIPE_FORMAT: Final = "station-recipe/1"
DEFAULT_RECIPE: Final = "default"
RECIPE_SUFFIX: Final = ".toml"


_NAME = re.compile(r"[a-z0-9][a-z0-9_-]*")
# ASCII digits only: ``\d`` would let other scripts' digits into a version.
_VERSION = re.compile(r"[0-9]+(\.[0-9]+)*")


class RecipeError(InputError):
    """A recipe cannot be used; every problem found is one line of the message.

    An ``InputError``: nothing has been done when it is raised (exit code 2).
    """

    def __init__(self, source: str, problems: Sequence[str]) -> None:
        self.source = source
        self.problems = tuple(problems)
        super().__init__("\n".join(f"{source}: {problem}" for problem in self.problems))


@dataclass(frozen=True)
class Product:
    name: str
    rated_current_mA: int
    microsteps: int
    rotor_teeth: int


@dataclass(frozen=True)
class Motion:
    """Speed and current of every hold; durations in electrical periods, because
    the demodulation integrates over whole periods."""

    electrical_hz: float
    amplitude_mA: int
    spin_up_periods: int
    settle_periods: int
    dwell_periods: int
    sensor_range_g: int


@dataclass(frozen=True)
class Clipping:
    """What the station may do when a hold clips at the sensor's full scale.

    A hold with more than ``max_share`` of its samples at full scale is not
    used: the analysis leaves clipped samples out, and what is left of a
    waveform cut at its peaks no longer pins its harmonics down. Such a point
    is measured again ``step_shrink`` of the way from its design's centre (a
    star's centre, an axis sweep's middle), where the ripple is lower, at most
    ``retries`` times; then it is left out and the estimators say whether the
    rest suffices. A recipe without this table does nothing but say it.
    """

    max_share: float
    step_shrink: float
    retries: int


@dataclass(frozen=True)
class SelfCheck:
    """The standstill check that the sensor is mounted and quiet before a run."""

    standstill_s: float
    gravity_tolerance_mps2: float
    max_noise_mps2: float


@dataclass(frozen=True)
class Verification:
    """The stored trims measured once more. ``settle_periods`` None (the key absent, as in
    recipes written before it existed) settles as long as a sweep's hold does."""

    dwell_periods: int
    settle_periods: int | None = None
    # The longest the station may go on measuring a unit whose two halves of the hold
    # still differ where it could decide the verdict (None, as in recipes written before
    # the key: the one hold); each further hold is ``dwell_periods`` long.
    max_dwell_periods: int | None = None
    # How often a unit whose verification fails a ripple limit may have its trims
    # corrected from that verification's own phasors and be verified again (0, as in
    # recipes written before the key: never).
    max_corrections: int = 0


@dataclass(frozen=True)
class Limits:
    """Pass/fail limits; the drift limits only warn (field service: how far the
    new trims moved from the previous ones)."""

    max_h1_after_mps2: float
    max_h2_after_mps2: float
    min_reduction_db: float
    offset_bound_mA: float
    gain_min: int
    gain_max: int
    max_offset_sigma_mA: float
    max_gain_sigma: float
    min_fit_r_squared: float
    max_drift_offset_mA: float
    max_drift_gain: float


@dataclass(frozen=True)
class Recipe:
    """A validated recipe together with the exact text it came from, so that a
    run can store the hash and the text can be found again."""

    name: str
    version: str
    description: str
    method: str  # a calibration method's name (station.methods.SWEEPS)
    product: Product
    motion: Motion
    sweep: Any  # the settings of the method's own table, read by its plug-in
    self_check: SelfCheck
    verification: Verification
    limits: Limits
    source: str
    text: str
    sha256: str
    # The angle-free method's settings, for benches that do not see the drive's angle.
    magnitude_sweep: Any = None
    clipping: Clipping | None = None  # None: clipped holds are used, and said

    @property
    def angle_free(self) -> bool:
        """Whether the recipe can calibrate a drive whose electrical angle is unknown."""
        from station.methods import sweep_method  # noqa: PLC0415 - the plug-ins

        return not sweep_method(self.method).needs_angle or self.magnitude_sweep is not None

    def hold_periods(self) -> int:
        """Electrical periods of one trim point: settling, then the measured dwell."""
        return self.motion.settle_periods + self.motion.dwell_periods


def _keys(cls: type) -> tuple[str, ...]:
    return tuple(f.name for f in fields(cls))


def _read_product(t: TomlTable) -> Product:
    product = Product(
        name=t.string("name", nonempty=True),
        rated_current_mA=t.integer("rated_current_mA", 1, 65535),
        microsteps=t.integer("microsteps", 1, 256),
        rotor_teeth=t.integer("rotor_teeth", 1, 1000),
    )
    t.finish()
    return product


def _read_motion(t: TomlTable, rated: int | None) -> Motion:
    motion = Motion(
        electrical_hz=t.real("electrical_hz", gt=0, le=50),
        amplitude_mA=t.integer(
            "amplitude_mA",
            1,
            rated,
            note="at most product.rated_current_mA" if rated is not None else "",
        ),
        spin_up_periods=t.integer("spin_up_periods", 0, 1000),
        settle_periods=t.integer("settle_periods", 0, 1000),
        dwell_periods=t.integer("dwell_periods", 3, 10000),
        sensor_range_g=t.integer("sensor_range_g", choices=SENSOR_RANGES_G),
    )
    t.finish()
    return motion


def _read_sweep(root: TomlTable, method: str | None, rated: int | None) -> Any:
    """The settings of the recipe's method, read by its plug-in (``station.methods``)
    from the table it names; keys of the other methods that share that table are named
    as theirs."""
    from station.methods import SWEEPS, sweep_method  # noqa: PLC0415 - imported when read

    if method is None:
        # Without a valid method the sweep's keys cannot be judged; the method's
        # own error says what to fix first.
        root.optional_table("sweep")
        return None
    chosen = sweep_method(method)
    t = root.table(chosen.table)
    settings = chosen.read(t, rated)
    others = [sweep_method(name) for name in SWEEPS if name != chosen.name]
    foreign = {key: f"not used by the {method} method" for other in others
               if other.table == chosen.table for key in _keys(other.settings_type)}
    t.finish(foreign)
    return settings


def _read_angle_free(root: TomlTable, method: str | None, rated: int | None) -> Any:
    """The angle-free method's settings (``magnitude_sweep``), for drives that do not
    report their angle; the recipe's own where its method is that one."""
    from station.methods import ANGLE_FREE, sweep_method  # noqa: PLC0415

    angle_free = sweep_method(ANGLE_FREE)
    if method == ANGLE_FREE:
        return None  # the recipe's sweep is it
    t = root.optional_table(angle_free.table)
    return None if t is None else angle_free.read(t, rated)


def _read_clipping(t: TomlTable | None) -> Clipping | None:
    if t is None:
        return None
    clipping = Clipping(
        max_share=t.real("max_share", ge=0, lt=1),
        step_shrink=t.real("step_shrink", gt=0, lt=1),
        retries=t.integer("retries", 0, 10),
    )
    t.finish()
    return clipping


def _read_self_check(t: TomlTable) -> SelfCheck:
    self_check = SelfCheck(
        standstill_s=t.real("standstill_s", gt=0, le=10),
        gravity_tolerance_mps2=t.real("gravity_tolerance_mps2", gt=0, lt=STANDARD_GRAVITY),
        max_noise_mps2=t.real("max_noise_mps2", gt=0),
    )
    t.finish()
    return self_check


def _read_verification(t: TomlTable) -> Verification:
    verification = Verification(
        dwell_periods=t.integer("dwell_periods", 3, 10000),
        settle_periods=(t.integer("settle_periods", 0, 1000) if t.has("settle_periods")
                        else None),
        max_dwell_periods=(t.integer("max_dwell_periods", 3, 10000)
                           if t.has("max_dwell_periods") else None),
        max_corrections=(t.integer("max_corrections", 0, 3)
                         if t.has("max_corrections") else 0),
    )
    longest = verification.max_dwell_periods
    if (longest is not None and t.valid("dwell_periods", "max_dwell_periods")
            and longest < verification.dwell_periods):
        t.problem("max_dwell_periods",
                  f"must be >= {t.name('dwell_periods')} ({verification.dwell_periods}): "
                  f"the first hold alone measures that long, got {longest}")
    t.finish()
    return verification


def _read_limits(t: TomlTable, rated: int | None) -> Limits:
    limits = Limits(
        max_h1_after_mps2=t.real("max_h1_after_mps2", gt=0),
        max_h2_after_mps2=t.real("max_h2_after_mps2", gt=0),
        min_reduction_db=t.real("min_reduction_db", ge=0),
        offset_bound_mA=t.real(
            "offset_bound_mA",
            gt=0,
            le=rated / 2 if rated is not None else None,
            note="at most half of product.rated_current_mA, the drive's offset range"
            if rated is not None
            else "",
        ),
        gain_min=t.integer("gain_min", *GAIN_LIMITS),
        gain_max=t.integer("gain_max", *GAIN_LIMITS),
        max_offset_sigma_mA=t.real("max_offset_sigma_mA", gt=0),
        max_gain_sigma=t.real("max_gain_sigma", gt=0),
        min_fit_r_squared=t.real("min_fit_r_squared", gt=0, lt=1),
        max_drift_offset_mA=t.real("max_drift_offset_mA", gt=0),
        max_drift_gain=t.real("max_drift_gain", gt=0),
    )
    span(t, ("gain_min", "gain_max"), (limits.gain_min, limits.gain_max), GAIN_UNITY)
    t.finish()
    return limits


def _decode_error(source: str, exc: tomllib.TOMLDecodeError) -> RecipeError:
    return RecipeError(source, [toml_error(exc)])


def parse_recipe(text: str, *, source: str = "<text>", expected_name: str | None = None) -> Recipe:
    """Validate a recipe's text completely, or raise one ``RecipeError`` listing
    every problem; ``expected_name`` is the file's stem, which the recipe's name
    must repeat so that a copied file cannot pose as its original."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise _decode_error(source, exc) from None

    problems: list[str] = []
    root = TomlTable(problems, "", data)
    recipe_format = root.string("format")
    if root.valid("format") and recipe_format != RECIPE_FORMAT:
        root.problem("format", f"must be {RECIPE_FORMAT!r}, got {recipe_format!r}")
    name = root.string("name", pattern=_NAME)
    if expected_name is not None and root.valid("name") and name != expected_name:
        root.problem("name", f"{name!r} must equal the file's name {expected_name!r}")
    version = root.string("version", pattern=_VERSION)
    description = root.string("description")
    from station.methods import SWEEPS  # noqa: PLC0415 - the plug-ins, by name

    method = root.one_of("method", SWEEPS)

    # Product first: the drive's ranges in the other tables follow from its
    # rated current, and only a valid one may bound them.
    product_table = root.table("product")
    product = _read_product(product_table)
    rated = product.rated_current_mA if product_table.valid("rated_current_mA") else None
    motion = _read_motion(root.table("motion"), rated)
    sweep = _read_sweep(root, method, rated)
    magnitude_sweep = _read_angle_free(root, method, rated)
    clipping = _read_clipping(root.optional_table("clipping"))
    self_check = _read_self_check(root.table("self_check"))
    verification = _read_verification(root.table("verification"))
    limits = _read_limits(root.table("limits"), rated)
    root.finish()

    # A bad method is always among the problems; the test also narrows the type.
    if problems or method is None:
        raise RecipeError(source, problems)
    return Recipe(
        name=name,
        version=version,
        description=description,
        method=method,
        product=product,
        motion=motion,
        sweep=sweep,
        self_check=self_check,
        verification=verification,
        limits=limits,
        source=source,
        text=text,
        sha256=hashlib.sha256(text.encode("utf-8")).hexdigest(),
        magnitude_sweep=magnitude_sweep,
        clipping=clipping,
    )


def available_recipes() -> list[str]:
    """Names of the recipes shipped with the station, for listing and lookup."""
    return sorted(
        entry.name.removesuffix(RECIPE_SUFFIX)
        for entry in files("recipes").iterdir()
        if entry.name.endswith(RECIPE_SUFFIX) and entry.is_file()
    )


def _is_path(name_or_path: str | Path) -> bool:
    if isinstance(name_or_path, Path):
        return True
    separators = {"/", os.sep} | ({os.altsep} if os.altsep else set())
    return name_or_path.endswith(RECIPE_SUFFIX) or any(s in name_or_path for s in separators)


def _decode(source: str, data: bytes) -> str:
    # Decoded from the bytes, not read as text: newline translation would make
    # the hash differ from the file's own SHA-256.
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise RecipeError(source, [f"not UTF-8 text (byte {exc.start})"]) from None


def load_recipe(name_or_path: str | Path) -> Recipe:
    """Load a shipped recipe by name, or any recipe file by path.

    A ``Path``, or a string with a path separator or the ``.toml`` suffix, is
    a file; a bare word is a shipped recipe, so an operator's ``--recipe paper`` cannot pick
    up a stray ``paper.toml`` from the working directory.
    """
    if _is_path(name_or_path):
        path = Path(name_or_path)
        source = str(path)
        try:
            data = path.read_bytes()
        except OSError as exc:
            raise RecipeError(source, [f"cannot read: {exc.strerror or exc}"]) from None
        return parse_recipe(_decode(source, data), source=source, expected_name=path.stem)

    # Shipped recipes are package data, so they are found from a wheel too.
    name = str(name_or_path)
    resource = files("recipes") / f"{name}{RECIPE_SUFFIX}"
    if not resource.is_file():
        listed = ", ".join(available_recipes()) or "none"
        raise RecipeError(name, [f"no such recipe; available: {listed}"])
    source = str(resource)
    return parse_recipe(_decode(source, resource.read_bytes()), source=source, expected_name=name)
