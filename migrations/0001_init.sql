-- tagdeflect archive, schema version 1: rigs, tests, frame sets (one per feed line, the
-- line kept whole as published), tag samples and gauge samples; the SPEC view feed_lines.
-- Applied by `tagdeflect archive` on start (see src/archive/db.rs); never edit a released
-- migration: add 0002_*.sql instead.

CREATE TABLE rigs (
    id          serial PRIMARY KEY,
    name        text NOT NULL UNIQUE,
    first_seen  timestamptz NOT NULL DEFAULT now(),
    status      jsonb,            -- the rig's latest status message (<topic>/status)
    status_at   timestamptz
);

CREATE TABLE tests (
    id          bigserial PRIMARY KEY,
    rig_id      integer NOT NULL REFERENCES rigs (id),
    name        text NOT NULL,    -- the test id of one run
    first_seen  timestamptz NOT NULL DEFAULT now(),
    status      jsonb,
    status_at   timestamptz,
    UNIQUE (rig_id, name)
);

CREATE TABLE frame_sets (
    test_id            bigint NOT NULL REFERENCES tests (id),
    seq                bigint NOT NULL,
    t_ns               bigint NOT NULL,
    load_kn            double precision,
    stroke_mm          double precision,
    net_deflection_mm  double precision,
    reproj_px          double precision,
    line               jsonb NOT NULL,   -- the feed line as published
    received_at        timestamptz NOT NULL DEFAULT now(),
    PRIMARY KEY (test_id, seq)
);
CREATE INDEX frame_sets_t_ns ON frame_sets (t_ns);

CREATE TABLE tag_samples (
    test_id     bigint NOT NULL,
    seq         bigint NOT NULL,
    tag_id      integer NOT NULL,
    t_ns        bigint NOT NULL,
    x_mm        double precision NOT NULL,
    y_mm        double precision NOT NULL,
    z_mm        double precision NOT NULL,
    dx_mm       double precision NOT NULL,
    dy_mm       double precision NOT NULL,
    dz_mm       double precision NOT NULL,
    sigma_x_mm  double precision,
    sigma_y_mm  double precision,
    sigma_z_mm  double precision,
    views       integer NOT NULL,
    reproj_px   double precision,
    PRIMARY KEY (test_id, seq, tag_id),
    FOREIGN KEY (test_id, seq) REFERENCES frame_sets (test_id, seq) ON DELETE CASCADE
);

CREATE TABLE gauge_samples (
    test_id  bigint NOT NULL,
    seq      bigint NOT NULL,
    name     text NOT NULL,
    t_ns     bigint NOT NULL,
    value    double precision,
    sigma    double precision,
    unit     text,
    PRIMARY KEY (test_id, seq, name),
    FOREIGN KEY (test_id, seq) REFERENCES frame_sets (test_id, seq) ON DELETE CASCADE
);

-- SPEC "Archive": one row per feed line, unique per (rig, test, seq).
CREATE VIEW feed_lines AS
    SELECT r.name AS rig, t.name AS test, f.seq, f.t_ns, f.line
    FROM frame_sets f
    JOIN tests t ON t.id = f.test_id
    JOIN rigs r ON r.id = t.rig_id;
