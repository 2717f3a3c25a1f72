-- tagdeflect archive, schema version 2: runs and gaps.
--
-- A run restarted with the same test id (a fixed `[output.mqtt] test`, or a restart after a
-- crash) numbers its lines from 0 again. A line whose (rig, test, seq) is already held with
-- a different t_ns belongs to a new run: every row now carries its `run` (1, 2, ... in the
-- order the archive met them) and the keys include it. The SPEC view `feed_lines` stays one
-- row per feed line, unique per (rig, test, seq): the lines of run 1 keep the test id as
-- published, those of a later run N show it as `<test>#N` ('#' cannot occur in a published
-- test id); the columns `run` and `published_test` say the same plainly.
--
-- `feed_gaps` lists, per (rig, test, run), every run of missing seqs: between held lines,
-- before the first held one (seqs count from 0) and, for a test's newest run, after the last
-- held one up to the `last_seq` the rig's retained status announced. Frame sets the rig
-- itself dropped (its solver fell behind: `dropped_sets` in the lines) have a seq but never
-- a line: `missing` counts only the lines a hole lacks beyond those, and a hole they explain
-- is no gap.

ALTER TABLE tag_samples DROP CONSTRAINT tag_samples_test_id_seq_fkey;
ALTER TABLE gauge_samples DROP CONSTRAINT gauge_samples_test_id_seq_fkey;

ALTER TABLE frame_sets ADD COLUMN run integer NOT NULL DEFAULT 1;
ALTER TABLE tag_samples ADD COLUMN run integer NOT NULL DEFAULT 1;
ALTER TABLE gauge_samples ADD COLUMN run integer NOT NULL DEFAULT 1;

ALTER TABLE frame_sets DROP CONSTRAINT frame_sets_pkey, ADD PRIMARY KEY (test_id, run, seq);
ALTER TABLE tag_samples DROP CONSTRAINT tag_samples_pkey, ADD PRIMARY KEY (test_id, run, seq, tag_id),
    ADD FOREIGN KEY (test_id, run, seq) REFERENCES frame_sets (test_id, run, seq) ON DELETE CASCADE;
ALTER TABLE gauge_samples DROP CONSTRAINT gauge_samples_pkey, ADD PRIMARY KEY (test_id, run, seq, name),
    ADD FOREIGN KEY (test_id, run, seq) REFERENCES frame_sets (test_id, run, seq) ON DELETE CASCADE;

DROP VIEW feed_lines;
-- SPEC "Archive": one row per feed line, unique per (rig, test, seq).
CREATE VIEW feed_lines AS
    SELECT r.name AS rig,
           CASE WHEN f.run = 1 THEN t.name ELSE t.name || '#' || f.run END AS test,
           f.seq, f.t_ns, f.line, f.run, t.name AS published_test
    FROM frame_sets f
    JOIN tests t ON t.id = f.test_id
    JOIN rigs r ON r.id = t.rig_id;

CREATE VIEW feed_gaps AS
    WITH d AS (
        SELECT test_id, run, seq,
               CASE WHEN jsonb_typeof(line->'dropped_sets') = 'number' THEN (line->>'dropped_sets')::bigint ELSE 0 END AS drops
        FROM frame_sets
    ), s AS (
        SELECT test_id, run, seq, drops,
               lag(seq) OVER (PARTITION BY test_id, run ORDER BY seq) AS prev,
               lag(drops) OVER (PARTITION BY test_id, run ORDER BY seq) AS prev_drops
        FROM d
    ), inner_gaps AS (
        SELECT test_id, run, coalesce(prev + 1, 0) AS first_seq, seq - 1 AS last_seq,
               (seq - coalesce(prev + 1, 0)) - greatest(drops - coalesce(prev_drops, 0), 0) AS missing
        FROM s WHERE seq > coalesce(prev + 1, 0)
          AND (seq - coalesce(prev + 1, 0)) > greatest(drops - coalesce(prev_drops, 0), 0)
    ), newest AS (
        SELECT f.test_id, f.run, max(f.seq) AS high
        FROM frame_sets f
        WHERE f.run = (SELECT max(run) FROM frame_sets g WHERE g.test_id = f.test_id)
        GROUP BY f.test_id, f.run
    ), tail AS (
        SELECT n.test_id, n.run, n.high + 1 AS first_seq, (t.status->>'last_seq')::bigint AS last_seq,
               (t.status->>'last_seq')::bigint - n.high AS missing
        FROM newest n JOIN tests t ON t.id = n.test_id
        WHERE jsonb_typeof(t.status->'last_seq') = 'number' AND (t.status->>'last_seq')::bigint > n.high
    ), gaps AS (
        SELECT test_id, run, first_seq, last_seq, missing, false AS tail FROM inner_gaps
        UNION ALL
        SELECT test_id, run, first_seq, last_seq, missing, true FROM tail
    )
    SELECT r.name AS rig,
           CASE WHEN g.run = 1 THEN t.name ELSE t.name || '#' || g.run END AS test,
           g.run, g.first_seq, g.last_seq, g.missing,
           g.tail AS after_last_held, t.name AS published_test
    FROM gaps g
    JOIN tests t ON t.id = g.test_id
    JOIN rigs r ON r.id = t.rig_id;
