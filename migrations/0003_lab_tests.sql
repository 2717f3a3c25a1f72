-- tagdeflect archive, schema version 3: the lab's tests (SPEC "Tests").
--
-- A lab test — one specimen from start to stop, kept by the rig in TESTS/<id>/ — is published
-- by the rig, retained, on `<topic>/labtest/<id>` (its test.json with the rig and the run) at
-- its start, at every event and at its stop. The table is `lab_tests` because `tests` holds the
-- runs (the MQTT test id of the topic) since schema 1. One row per (rig, lab test id): the
-- newest record (a record with fewer events than the one held is an older one and is left).
-- `lab_test_lines` is every archived feed line of a lab test (the lines carry `test.id`),
-- with its specimen.

CREATE TABLE lab_tests (
    rig_id        integer NOT NULL REFERENCES rigs (id),
    id            text NOT NULL,                 -- the test's id, e.g. 20261202T101500Z-B12
    run_test_id   bigint REFERENCES tests (id),  -- the run it was last published in
    specimen      text NOT NULL,
    operator      text,
    standard      text,
    notes         text,
    measured      jsonb,                         -- {"width_mm": 150.2, ...}
    started_t_ns  bigint NOT NULL,
    stopped_t_ns  bigint,                        -- null while it runs
    events        jsonb NOT NULL,                -- [{"kind", "t_ns", "note"}, ...]
    sha256        jsonb,                         -- {"feed.jsonl": "<hex>", ...} once stopped
    record        jsonb NOT NULL,                -- the message as published
    first_seen    timestamptz NOT NULL DEFAULT now(),
    updated_at    timestamptz NOT NULL DEFAULT now(),
    PRIMARY KEY (rig_id, id)
);

CREATE INDEX frame_sets_lab_test ON frame_sets ((line->'test'->>'id')) WHERE line ? 'test';

CREATE VIEW lab_test_lines AS
    SELECT r.name AS rig, lt.id AS lab_test, lt.specimen, t.name AS published_test, f.run, f.seq, f.t_ns, f.line
    FROM lab_tests lt
    JOIN rigs r ON r.id = lt.rig_id
    JOIN tests t ON t.rig_id = lt.rig_id
    JOIN frame_sets f ON f.test_id = t.id AND f.line ? 'test' AND f.line->'test'->>'id' = lt.id;
