-- QA's statistics are summed by the database (station/statsql.py). Over a line's
-- million runs, reading the wide rows is most of the time; this index holds exactly
-- what the sums read, grouped as they group, so a vacuumed table is summed from the
-- index alone. The filter's columns are included: a question by date or station stays
-- on the index.
CREATE INDEX runs_for_statistics ON runs (recipe_sha256, verdict, trims_stored)
    INCLUDE (trims_after_offset_a_ma, trims_after_offset_b_ma, trims_after_gain_a,
             trims_after_gain_b, after_h1, after_h2, started_at, station_id, recipe_name,
             serial);

-- The bounds a recipe's newest run was judged by: found from its newest run backwards.
CREATE INDEX runs_by_recipe_hash ON runs (recipe_sha256, started_at);

-- ... or, for a check its newest runs lack, from the newest such check backwards.
CREATE INDEX limit_checks_by_name ON limit_checks (name, run_id);
