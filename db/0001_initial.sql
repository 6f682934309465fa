-- The station's results: one row per calibration attempt, the recipes they
-- followed, the limits each run was judged against, and field verifications.
-- Times are UTC ISO 8601 text with a 'Z' to the microsecond (station.runs.utc_iso),
-- so that they sort as text. Trims and ripple are spread over REAL columns so
-- that QA can query them without parsing JSON.

-- The exact text of every recipe ever used, so a run can be re-read against it.
CREATE TABLE recipes (
    sha256        TEXT PRIMARY KEY,
    name          TEXT NOT NULL,
    version       TEXT NOT NULL,
    text          TEXT NOT NULL,
    first_used_at TEXT NOT NULL
);

CREATE TABLE runs (
    run_id            INTEGER PRIMARY KEY,
    -- What is known when the run begins.
    serial            TEXT NOT NULL,
    kind              TEXT NOT NULL CHECK (kind IN ('calibrate', 'recalibrate')),
    recipe_name       TEXT NOT NULL,
    recipe_version    TEXT NOT NULL,
    recipe_sha256     TEXT NOT NULL REFERENCES recipes (sha256),
    station_id        INTEGER NOT NULL,
    operator          TEXT NOT NULL,
    software_version  TEXT NOT NULL,
    bench             TEXT NOT NULL,
    started_at        TEXT NOT NULL,
    service_reason    TEXT,
    previous_run_id   INTEGER REFERENCES runs (run_id),
    -- What the run learnt; NULL verdict while it runs (or if the station died).
    finished_at       TEXT,
    verdict           TEXT CHECK (verdict IN ('pass', 'fail', 'error', 'aborted')),
    reason            TEXT,
    trims_before_offset_a_mA    REAL,
    trims_before_offset_b_mA    REAL,
    trims_before_gain_a         REAL,
    trims_before_gain_b         REAL,
    trims_after_offset_a_mA     REAL,
    trims_after_offset_b_mA     REAL,
    trims_after_gain_a          REAL,
    trims_after_gain_b          REAL,
    trims_estimated_offset_a_mA REAL,
    trims_estimated_offset_b_mA REAL,
    trims_estimated_gain_a      REAL,
    trims_estimated_gain_b      REAL,
    uncertainty_offset_a_mA     REAL,
    uncertainty_offset_b_mA     REAL,
    uncertainty_gain_a          REAL,
    uncertainty_gain_b          REAL,
    trims_stored      INTEGER NOT NULL DEFAULT 0 CHECK (trims_stored IN (0, 1)),
    before_h1         REAL,
    before_h2         REAL,
    after_h1          REAL,
    after_h2          REAL,
    method            TEXT,
    fit               TEXT,  -- JSON object, or NULL
    warnings          TEXT NOT NULL DEFAULT '[]',  -- JSON array of strings
    recording         TEXT,
    recording_sha256  TEXT,
    motion_s          REAL
);

-- A unit's history is the station's most frequent question.
CREATE INDEX runs_by_serial ON runs (serial, run_id);
CREATE INDEX runs_by_start ON runs (started_at);
CREATE INDEX runs_by_recipe ON runs (recipe_name, started_at);
CREATE INDEX runs_by_station ON runs (station_id, started_at);

-- passed NULL: the limit did not apply. position keeps the order the recipe gave.
CREATE TABLE limit_checks (
    run_id    INTEGER NOT NULL REFERENCES runs (run_id) ON DELETE CASCADE,
    name      TEXT NOT NULL,
    position  INTEGER NOT NULL,
    value     REAL,
    low       REAL,
    high      REAL,
    unit      TEXT NOT NULL,
    passed    INTEGER CHECK (passed IN (0, 1)),
    note      TEXT NOT NULL DEFAULT '',
    PRIMARY KEY (run_id, name)
) WITHOUT ROWID;

-- A unit back from the field whose drive trims were compared with the record.
CREATE TABLE verifications (
    verification_id   INTEGER PRIMARY KEY,
    serial            TEXT NOT NULL,
    verified_at       TEXT NOT NULL,
    station_id        INTEGER NOT NULL,
    operator          TEXT NOT NULL,
    bench             TEXT NOT NULL,
    trims_match       INTEGER NOT NULL CHECK (trims_match IN (0, 1)),
    drive_offset_a_mA REAL NOT NULL,
    drive_offset_b_mA REAL NOT NULL,
    drive_gain_a      REAL NOT NULL,
    drive_gain_b      REAL NOT NULL,
    recorded_run_id   INTEGER REFERENCES runs (run_id),
    recorded_offset_a_mA REAL,
    recorded_offset_b_mA REAL,
    recorded_gain_a      REAL,
    recorded_gain_b      REAL
);

CREATE INDEX verifications_by_serial ON verifications (serial, verification_id);
