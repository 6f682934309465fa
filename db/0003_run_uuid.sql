-- Every run carries a UUID from the moment it is created, wherever it is stored: a
-- run a station spooled while the line's database was out of reach, and forwarded
-- later, is the same run there, and a second forward of it is refused instead of
-- recorded twice. Runs recorded before this migration have none (NULL): they were
-- only ever in this file.
ALTER TABLE runs ADD COLUMN run_uuid TEXT;

CREATE UNIQUE INDEX runs_by_uuid ON runs (run_uuid);

-- Like everything known when the run began, its identity is never rewritten.
CREATE TRIGGER runs_uuid_is_final
BEFORE UPDATE OF run_uuid ON runs
BEGIN
    SELECT RAISE(ABORT, 'runs are append-only: what a run recorded when it began cannot be changed');
END;
