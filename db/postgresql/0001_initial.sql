-- A line's central results database: the same tables, columns and rules as a
-- station's SQLite file (db/0001-0003), in PostgreSQL's types. Many stations write
-- here at once; QA reads the whole line. Times are timestamptz (the station reads
-- and writes them as UTC), booleans boolean, trims and ripple double precision.
-- Column names are those of the SQLite schema, folded to lower case by PostgreSQL.

CREATE TABLE recipes (
    sha256        text PRIMARY KEY,
    name          text NOT NULL,
    version       text NOT NULL,
    text          text NOT NULL,
    first_used_at timestamptz NOT NULL
);

CREATE TABLE runs (
    run_id            bigint GENERATED ALWAYS AS IDENTITY PRIMARY KEY,
    -- Who the run is, on every station and here: a forwarded run is never recorded twice.
    run_uuid          uuid UNIQUE,
    serial            text NOT NULL,
    kind              text NOT NULL CHECK (kind IN ('calibrate', 'recalibrate')),
    recipe_name       text NOT NULL,
    recipe_version    text NOT NULL,
    recipe_sha256     text NOT NULL REFERENCES recipes (sha256),
    station_id        integer NOT NULL,
    operator          text NOT NULL,
    software_version  text NOT NULL,
    bench             text NOT NULL,
    started_at        timestamptz NOT NULL,
    service_reason    text,
    previous_run_id   bigint REFERENCES runs (run_id),
    owner             text,  -- JSON: the process that began it (see db/README.md)
    finished_at       timestamptz,
    verdict           text CHECK (verdict IN ('pass', 'fail', 'error', 'aborted')),
    reason            text,
    trims_before_offset_a_mA    double precision,
    trims_before_offset_b_mA    double precision,
    trims_before_gain_a         double precision,
    trims_before_gain_b         double precision,
    trims_after_offset_a_mA     double precision,
    trims_after_offset_b_mA     double precision,
    trims_after_gain_a          double precision,
    trims_after_gain_b          double precision,
    trims_estimated_offset_a_mA double precision,
    trims_estimated_offset_b_mA double precision,
    trims_estimated_gain_a      double precision,
    trims_estimated_gain_b      double precision,
    uncertainty_offset_a_mA     double precision,
    uncertainty_offset_b_mA     double precision,
    uncertainty_gain_a          double precision,
    uncertainty_gain_b          double precision,
    trims_stored      boolean NOT NULL DEFAULT false,
    before_h1         double precision,
    before_h2         double precision,
    after_h1          double precision,
    after_h2          double precision,
    method            text,
    fit               text,  -- JSON object, or NULL
    warnings          text NOT NULL DEFAULT '[]',  -- JSON array of strings
    recording         text,  -- on the station's disk: its path there, and its hash here
    recording_sha256  text,
    motion_s          double precision
);

CREATE INDEX runs_by_serial ON runs (serial, run_id);
CREATE INDEX runs_by_start ON runs (started_at);
CREATE INDEX runs_by_recipe ON runs (recipe_name, started_at);
CREATE INDEX runs_by_station ON runs (station_id, started_at);
CREATE INDEX runs_open ON runs (run_id) WHERE verdict IS NULL;

CREATE TABLE limit_checks (
    run_id    bigint NOT NULL REFERENCES runs (run_id),
    name      text NOT NULL,
    position  integer NOT NULL,
    value     double precision,
    low       double precision,
    high      double precision,
    unit      text NOT NULL,
    passed    boolean,
    note      text NOT NULL DEFAULT '',
    PRIMARY KEY (run_id, name)
);

CREATE TABLE verifications (
    verification_id   bigint GENERATED ALWAYS AS IDENTITY PRIMARY KEY,
    serial            text NOT NULL,
    verified_at       timestamptz NOT NULL,
    station_id        integer NOT NULL,
    operator          text NOT NULL,
    bench             text NOT NULL,
    trims_match       boolean NOT NULL,
    drive_offset_a_mA double precision NOT NULL,
    drive_offset_b_mA double precision NOT NULL,
    drive_gain_a      double precision NOT NULL,
    drive_gain_b      double precision NOT NULL,
    recorded_run_id   bigint REFERENCES runs (run_id),
    recorded_offset_a_mA double precision,
    recorded_offset_b_mA double precision,
    recorded_gain_a      double precision,
    recorded_gain_b      double precision
);

CREATE INDEX verifications_by_serial ON verifications (serial, verification_id);

-- Append-only, as in db/0002: enforced by the server for every client (the
-- station, psql, a report tool), with the same messages. An open run (verdict
-- NULL) is finished once; nothing it recorded when it began changes, ever.
CREATE FUNCTION runs_append_only() RETURNS trigger LANGUAGE plpgsql AS $$
BEGIN
    IF TG_OP = 'DELETE' THEN
        RAISE EXCEPTION 'runs are append-only: a run cannot be deleted';
    END IF;
    IF OLD.verdict IS NOT NULL THEN
        RAISE EXCEPTION 'runs are append-only: a finished run (verdict set) cannot be changed';
    END IF;
    IF (NEW.run_id, NEW.run_uuid, NEW.serial, NEW.kind, NEW.recipe_name, NEW.recipe_version,
        NEW.recipe_sha256, NEW.station_id, NEW.operator, NEW.software_version, NEW.bench,
        NEW.started_at, NEW.service_reason, NEW.previous_run_id, NEW.owner)
       IS DISTINCT FROM
       (OLD.run_id, OLD.run_uuid, OLD.serial, OLD.kind, OLD.recipe_name, OLD.recipe_version,
        OLD.recipe_sha256, OLD.station_id, OLD.operator, OLD.software_version, OLD.bench,
        OLD.started_at, OLD.service_reason, OLD.previous_run_id, OLD.owner) THEN
        RAISE EXCEPTION 'runs are append-only: what a run recorded when it began cannot be changed';
    END IF;
    RETURN NEW;
END
$$;

CREATE TRIGGER runs_append_only BEFORE UPDATE OR DELETE ON runs
    FOR EACH ROW EXECUTE FUNCTION runs_append_only();

CREATE FUNCTION refuse_change() RETURNS trigger LANGUAGE plpgsql AS $$
BEGIN
    RAISE EXCEPTION '% are append-only: a recorded row cannot be changed or deleted (%)',
        TG_TABLE_NAME, TG_OP;
END
$$;

CREATE TRIGGER limit_checks_are_final BEFORE UPDATE OR DELETE ON limit_checks
    FOR EACH ROW EXECUTE FUNCTION refuse_change();
CREATE TRIGGER verifications_are_final BEFORE UPDATE OR DELETE ON verifications
    FOR EACH ROW EXECUTE FUNCTION refuse_change();
CREATE TRIGGER recipes_are_final BEFORE UPDATE OR DELETE ON recipes
    FOR EACH ROW EXECUTE FUNCTION refuse_change();
-- TRUNCATE fires no row triggers: refused per statement.
CREATE TRIGGER runs_not_truncated BEFORE TRUNCATE ON runs
    FOR EACH STATEMENT EXECUTE FUNCTION refuse_change();
CREATE TRIGGER limit_checks_not_truncated BEFORE TRUNCATE ON limit_checks
    FOR EACH STATEMENT EXECUTE FUNCTION refuse_change();
CREATE TRIGGER verifications_not_truncated BEFORE TRUNCATE ON verifications
    FOR EACH STATEMENT EXECUTE FUNCTION refuse_change();
CREATE TRIGGER recipes_not_truncated BEFORE TRUNCATE ON recipes
    FOR EACH STATEMENT EXECUTE FUNCTION refuse_change();

-- A finished run is not given more limit checks than it was judged on.
CREATE FUNCTION limit_checks_only_for_open_runs() RETURNS trigger LANGUAGE plpgsql AS $$
BEGIN
    IF (SELECT verdict FROM runs WHERE run_id = NEW.run_id) IS NOT NULL THEN
        RAISE EXCEPTION 'limit checks are append-only: a finished run cannot be given more limit checks';
    END IF;
    RETURN NEW;
END
$$;

CREATE TRIGGER limit_checks_only_for_open_runs BEFORE INSERT ON limit_checks
    FOR EACH ROW EXECUTE FUNCTION limit_checks_only_for_open_runs();
