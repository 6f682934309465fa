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
from typing import Final

from station.core import (
    GAIN_LIMITS,
    GAIN_UNITY,
    SENSOR_RANGES_G,
    STANDARD_GRAVITY,
    Method,
    offset_limit_mA,
)
from station.errors import InputError
from station.tomltable import TomlTable, toml_error

RECIPE_FORMAT: Final = "station-recipe/1"
DEFAULT_RECIPE: Final = "default"
RECIPE_SUFFIX: Final = ".toml"

# Sum of the two phase gains during the paper's gain sweep: the mean torque stays
# constant (the paper's step 3, I21 = 2I - I11).
GAIN_SUM: Final = 2 * GAIN_UNITY
MAX_COHERENT_ROUNDS: Final = 5
MAX_SIGMA_ROUNDS: Final = 3
MAX_GAIN_STEP: Final = 5000

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
class PaperSweep:
    """The paper's three sweeps, closed loop: offset A over [min, max] with B at
    0, then B with A at its estimate, then gain A over [gain_min, gain_max] with
    gain B = 20000 - gain A and the offsets at their estimates."""

    offset_min_mA: int
    offset_max_mA: int
    offset_points: int
    gain_min: int
    gain_max: int
    gain_points: int


@dataclass(frozen=True)
class CoherentSweep:
    """One round per entry: a star design (±step on offset A, on offset B and on
    the gain split) around the latest estimate; later rounds use smaller steps
    to measure the slopes close to the null."""

    offset_steps_mA: tuple[int, ...]
    gain_steps: tuple[int, ...]
    # Rounds added around the latest estimate while its σ is over the recipe's limit:
    # a unit that moves the load little per mA (a belt) is short of information. Each
    # is the widest of the rounds' stars that the maps still explain, which tells the
    # slopes most per hold.
    sigma_rounds: int = 0


@dataclass(frozen=True)
class MagnitudeSweep:
    """The paper's parabolas where the drive's electrical angle is unknown (a Modbus
    drive): per round, offset A, then offset B, then the gain split, each swept
    over ±span in ``points`` steps around the latest estimate, so the last round's
    parabolas sit close to the null where they are nearly exact."""

    offset_spans_mA: tuple[int, ...]
    gain_spans: tuple[int, ...]
    points: int
    # Holds of its own (None: the motion table's). A trim written over Modbus takes
    # effect somewhere between its sending and its acknowledgement, and those samples
    # are not used, so these holds cannot be as short as a CANopen star's.
    settle_periods: int | None = None
    dwell_periods: int | None = None


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
    method: Method
    product: Product
    motion: Motion
    sweep: PaperSweep | CoherentSweep
    self_check: SelfCheck
    verification: Verification
    limits: Limits
    source: str
    text: str
    sha256: str
    magnitude_sweep: MagnitudeSweep | None = None  # for benches that see no drive angle
    clipping: Clipping | None = None  # None: clipped holds are used, and said

    @property
    def angle_free(self) -> bool:
        """Whether the recipe can calibrate a drive whose electrical angle is unknown."""
        return isinstance(self.sweep, PaperSweep) or self.magnitude_sweep is not None

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


def _span(t: TomlTable, keys: tuple[str, str], values: tuple[int, int], through: int) -> None:
    """A [min, max] pair must be ordered and contain ``through`` (nominal): the
    paper's parabolas need the untrimmed unit's own ripple, and gain limits
    that exclude 10000 would fail every unit that needs no gain trim."""
    low_key, high_key = keys
    low, high = values
    if not t.valid(low_key, high_key):
        return
    if low >= high:
        t.problem(low_key, f"must be less than {t.name(high_key)} ({high}), got {low}")
    elif low > through:
        t.problem(low_key, f"must be <= {through}: the range {low}..{high} must contain {through}")
    elif high < through:
        t.problem(high_key, f"must be >= {through}: the range {low}..{high} must contain {through}")


def _neg(value: int | None) -> int | None:
    return None if value is None else -value


def _read_paper_sweep(t: TomlTable, rated: int | None) -> PaperSweep:
    half = offset_limit_mA(rated) if rated is not None else None
    offset_note = "the drive's offset range: half of product.rated_current_mA"
    offset_note = offset_note if half is not None else ""
    # 20000 - g lies in 5000..15000 exactly when g does, so one range check covers
    # both phases' gains.
    gain_note = f"and gain B = {GAIN_SUM} - gain A must be too"
    sweep = PaperSweep(
        offset_min_mA=t.integer("offset_min_mA", _neg(half), half, note=offset_note),
        offset_max_mA=t.integer("offset_max_mA", _neg(half), half, note=offset_note),
        offset_points=t.integer("offset_points", 3, 101),
        gain_min=t.integer("gain_min", *GAIN_LIMITS, note=gain_note),
        gain_max=t.integer("gain_max", *GAIN_LIMITS, note=gain_note),
        gain_points=t.integer("gain_points", 3, 101),
    )
    offsets = (sweep.offset_min_mA, sweep.offset_max_mA)
    _span(t, ("offset_min_mA", "offset_max_mA"), offsets, 0)
    _span(t, ("gain_min", "gain_max"), (sweep.gain_min, sweep.gain_max), GAIN_UNITY)
    return sweep


def _read_coherent_sweep(t: TomlTable, rated: int | None) -> CoherentSweep:
    half = offset_limit_mA(rated) if rated is not None else None
    sweep = CoherentSweep(
        offset_steps_mA=_read_rounds(t, "offset_steps_mA", half,
                                     "at most half of product.rated_current_mA"),
        gain_steps=_read_rounds(t, "gain_steps", MAX_GAIN_STEP, ""),
        sigma_rounds=t.integer("sigma_rounds", 0, MAX_SIGMA_ROUNDS) if t.has("sigma_rounds") else 0,
    )
    rounds_a, rounds_b = len(sweep.offset_steps_mA), len(sweep.gain_steps)
    if t.valid("offset_steps_mA", "gain_steps") and rounds_a and rounds_b and rounds_a != rounds_b:
        t.problem(
            "gain_steps",
            f"must have as many rounds as {t.name('offset_steps_mA')} ({rounds_a}), got {rounds_b}",
        )
    return sweep


def _read_rounds(t: TomlTable, key: str, high: int | None, note: str) -> tuple[int, ...]:
    steps = t.int_array(key)
    if not t.valid(key):
        return steps  # a mistyped element was reported already
    if not steps:
        t.problem(key, "must not be empty: one entry per round")
    elif len(steps) > MAX_COHERENT_ROUNDS:
        t.problem(key, f"must have at most {MAX_COHERENT_ROUNDS} rounds, got {len(steps)}")
    for i, step in enumerate(steps):
        t.check_int(f"{key}[{i}]", step, 1, high, note=note if high is not None else "")
    return steps


def _read_magnitude_sweep(t: TomlTable | None, rated: int | None) -> MagnitudeSweep | None:
    if t is None:
        return None
    half = offset_limit_mA(rated) if rated is not None else None
    sweep = MagnitudeSweep(
        offset_spans_mA=_read_rounds(t, "offset_spans_mA", half,
                                     "at most half of product.rated_current_mA"),
        gain_spans=_read_rounds(t, "gain_spans", MAX_GAIN_STEP, ""),
        points=t.integer("points", 3, 21),
        settle_periods=(t.integer("settle_periods", 0, 1000) if t.has("settle_periods")
                        else None),
        dwell_periods=(t.integer("dwell_periods", 3, 10000) if t.has("dwell_periods")
                       else None),
    )
    rounds_a, rounds_b = len(sweep.offset_spans_mA), len(sweep.gain_spans)
    if t.valid("offset_spans_mA", "gain_spans") and rounds_a and rounds_b and rounds_a != rounds_b:
        t.problem("gain_spans", f"must have as many rounds as {t.name('offset_spans_mA')} "
                  f"({rounds_a}), got {rounds_b}")
    t.finish()
    return sweep


def _read_sweep(
    t: TomlTable, method: Method | None, rated: int | None
) -> PaperSweep | CoherentSweep:
    sweep: PaperSweep | CoherentSweep
    if method is Method.PAPER:
        sweep = _read_paper_sweep(t, rated)
        other = _keys(CoherentSweep)
    elif method is Method.COHERENT:
        sweep = _read_coherent_sweep(t, rated)
        other = _keys(PaperSweep)
    else:
        # Without a valid method the sweep's keys cannot be judged; the method's
        # own error says what to fix first.
        return CoherentSweep((), ())
    t.finish(dict.fromkeys(other, f"not used by the {method} method"))
    return sweep


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
    _span(t, ("gain_min", "gain_max"), (limits.gain_min, limits.gain_max), GAIN_UNITY)
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
    method = root.choice("method", Method)

    # Product first: the drive's ranges in the other tables follow from its
    # rated current, and only a valid one may bound them.
    product_table = root.table("product")
    product = _read_product(product_table)
    rated = product.rated_current_mA if product_table.valid("rated_current_mA") else None
    motion = _read_motion(root.table("motion"), rated)
    sweep = _read_sweep(root.table("sweep"), method, rated)
    magnitude_sweep = _read_magnitude_sweep(root.optional_table("magnitude_sweep"), rated)
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
