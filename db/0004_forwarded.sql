-- A station whose line database (PostgreSQL) was out of reach records its runs in a
-- spool of its own, this schema in $STATION_HOME/spool.db, and forwards them later
-- (station/spool.py). Which were forwarded, where and under which number there, is a
-- row here: appended once, never changed, so a run is forwarded exactly once even if
-- the station stops between the line's commit and this one (the line refuses a
-- second copy of a run by its UUID). Empty in a station's own database.
CREATE TABLE forwarded (
    run_id              INTEGER PRIMARY KEY REFERENCES runs (run_id),
    forwarded_at        TEXT NOT NULL,
    destination         TEXT NOT NULL,  -- the line's database, without its password
    destination_run_id  INTEGER NOT NULL
);

CREATE TRIGGER forwarded_is_final
BEFORE UPDATE ON forwarded
BEGIN
    SELECT RAISE(ABORT, 'forwarded runs are append-only: a forwarding cannot be changed');
END;

CREATE TRIGGER forwarded_is_never_deleted
BEFORE DELETE ON forwarded
BEGIN
    SELECT RAISE(ABORT, 'forwarded runs are append-only: a forwarding cannot be deleted');
END;
