-- Finished runs are the station's traceability record: once a run has a
-- verdict, nothing may change or remove it, whoever holds the file (the
-- station, a script, a technician with the sqlite3 shell). SQLite enforces
-- it with triggers, so the rule holds for every connection, not only for
-- station/store.py. An open run (verdict NULL) may be finished, once.

-- Who is running an open run: a small JSON object
-- {"host", "boot_id", "pid", "start_time", "pid_ns"} written by Store.begin_run,
-- so the next start can tell whether that process is provably gone and finish
-- its run as 'aborted' (see db/README.md, "Interrupted runs"). NULL on rows
-- written before this migration: such an open run is never finished for it.
ALTER TABLE runs ADD COLUMN owner TEXT;

-- The open runs, found at every begin_run without scanning a million finished ones.
CREATE INDEX runs_open ON runs (run_id) WHERE verdict IS NULL;

-- INSERT OR REPLACE (or REPLACE INTO) removes the row it collides with without
-- firing DELETE triggers (unless a connection turns recursive_triggers on), so
-- a row is also protected from being replaced by a new one with its key. (A key
-- SQLite is about to choose reads -1 in a BEFORE INSERT trigger; real ones are > 0.)
CREATE TRIGGER runs_are_never_replaced
BEFORE INSERT ON runs
WHEN NEW.run_id > 0 AND EXISTS (SELECT 1 FROM runs WHERE run_id = NEW.run_id)
BEGIN
    SELECT RAISE(ABORT, 'runs are append-only: a run cannot be replaced');
END;

-- A finished run cannot be changed.
CREATE TRIGGER runs_finished_are_final
BEFORE UPDATE ON runs
WHEN OLD.verdict IS NOT NULL
BEGIN
    SELECT RAISE(ABORT, 'runs are append-only: a finished run (verdict set) cannot be changed');
END;

-- What was known when a run began is never rewritten, even while it is open.
CREATE TRIGGER runs_start_is_final
BEFORE UPDATE OF run_id, serial, kind, recipe_name, recipe_version, recipe_sha256, station_id,
    operator, software_version, bench, started_at, service_reason, previous_run_id, owner
ON runs
BEGIN
    SELECT RAISE(ABORT, 'runs are append-only: what a run recorded when it began cannot be changed');
END;

-- No run is ever removed, open or finished.
CREATE TRIGGER runs_are_never_deleted
BEFORE DELETE ON runs
BEGIN
    SELECT RAISE(ABORT, 'runs are append-only: a run cannot be deleted');
END;

-- Limit checks are written once, as the run is finished, and never changed after.
CREATE TRIGGER limit_checks_are_final
BEFORE UPDATE ON limit_checks
BEGIN
    SELECT RAISE(ABORT, 'limit checks are append-only: a limit check cannot be changed');
END;

CREATE TRIGGER limit_checks_are_never_deleted
BEFORE DELETE ON limit_checks
BEGIN
    SELECT RAISE(ABORT, 'limit checks are append-only: a limit check cannot be deleted');
END;

CREATE TRIGGER limit_checks_are_never_replaced
BEFORE INSERT ON limit_checks
WHEN EXISTS (SELECT 1 FROM limit_checks WHERE run_id = NEW.run_id AND name = NEW.name)
BEGIN
    SELECT RAISE(ABORT, 'limit checks are append-only: a limit check cannot be replaced');
END;

-- Nor can a finished run be given more limit checks than it was judged on.
CREATE TRIGGER limit_checks_only_for_open_runs
BEFORE INSERT ON limit_checks
WHEN (SELECT verdict FROM runs WHERE run_id = NEW.run_id) IS NOT NULL
BEGIN
    SELECT RAISE(ABORT, 'limit checks are append-only: a finished run cannot be given more limit checks');
END;

CREATE TRIGGER verifications_are_never_replaced
BEFORE INSERT ON verifications
WHEN NEW.verification_id > 0
    AND EXISTS (SELECT 1 FROM verifications WHERE verification_id = NEW.verification_id)
BEGIN
    SELECT RAISE(ABORT, 'verifications are append-only: a verification cannot be replaced');
END;

CREATE TRIGGER verifications_are_final
BEFORE UPDATE ON verifications
BEGIN
    SELECT RAISE(ABORT, 'verifications are append-only: a verification cannot be changed');
END;

CREATE TRIGGER verifications_are_never_deleted
BEFORE DELETE ON verifications
BEGIN
    SELECT RAISE(ABORT, 'verifications are append-only: a verification cannot be deleted');
END;

-- A run finds its recipe again by hash: the text under a hash is fixed forever.
-- A second insert of a known hash is skipped (IGNORE, not ABORT): that is how
-- Store.begin_run keeps each text once (INSERT OR IGNORE), and it turns a
-- REPLACE of a stored recipe into a no-op instead of a silent rewrite.
CREATE TRIGGER recipes_are_never_replaced
BEFORE INSERT ON recipes
WHEN EXISTS (SELECT 1 FROM recipes WHERE sha256 = NEW.sha256)
BEGIN
    SELECT RAISE(IGNORE);
END;

CREATE TRIGGER recipes_are_final
BEFORE UPDATE ON recipes
BEGIN
    SELECT RAISE(ABORT, 'recipes are append-only: a stored recipe text cannot be changed');
END;

CREATE TRIGGER recipes_are_never_deleted
BEFORE DELETE ON recipes
BEGIN
    SELECT RAISE(ABORT, 'recipes are append-only: a stored recipe text cannot be deleted');
END;
