//! The archive's PostgreSQL side: schema migrations (applied on connect, versioned,
//! idempotent, serialised between several archives by an advisory lock) and the batched
//! upsert of feed lines.

use std::collections::HashMap;

use tokio_postgres::{Client, NoTls, Statement};

/// The schema migrations in order: (version, name, SQL). Files live in the workspace's
/// `migrations/`.
pub const MIGRATIONS: &[(i32, &str, &str)] = &[(1, "init", include_str!("../../../migrations/0001_init.sql"))];

/// Advisory lock key held while migrating ("tagdefle" in ASCII).
const MIGRATION_LOCK: i64 = 0x7461_6764_6566_6c65;

/// One feed line ready for the database.
#[derive(Debug, Clone)]
pub struct LineRow {
    /// Rig name (from the topic).
    pub rig: String,
    /// Test id (from the topic).
    pub test: String,
    /// Frame-set number.
    pub seq: i64,
    /// The line as published.
    pub line: serde_json::Value,
}

/// A status message for the database.
#[derive(Debug, Clone)]
pub struct StatusRow {
    /// Rig name (from the topic).
    pub rig: String,
    /// Test id (from the topic).
    pub test: String,
    /// The message (JSON object).
    pub status: serde_json::Value,
}

/// What one committed batch did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Written {
    /// Feed lines inserted (new).
    pub inserted: u64,
    /// Feed lines already stored (redelivered), left as they were.
    pub duplicates: u64,
    /// Tag samples inserted.
    pub tags: u64,
    /// Gauge samples inserted.
    pub gauges: u64,
    /// Rows refused by the database as bad data (logged, skipped).
    pub rejected: u64,
}

/// A connection to the archive database.
pub struct Db {
    client: Client,
    conn: tokio::task::JoinHandle<()>,
    insert: Statement,
    tests: HashMap<(String, String), i64>,
}

const INSERT_SQL: &str = r#"
WITH src AS (
    SELECT * FROM unnest($1::bigint[], $2::bigint[], $3::jsonb[]) AS s(test_id, seq, line)
), ins AS (
    INSERT INTO frame_sets (test_id, seq, t_ns, load_kn, stroke_mm, net_deflection_mm, reproj_px, line)
    SELECT test_id, seq, (line->>'t_ns')::bigint, (line->>'load_kN')::float8, (line->>'stroke_mm')::float8,
           (line->>'net_deflection_mm')::float8, (line->>'reproj_px')::float8, line
    FROM src
    ON CONFLICT (test_id, seq) DO NOTHING
    RETURNING test_id, seq, t_ns, line
), tags AS (
    INSERT INTO tag_samples (test_id, seq, tag_id, t_ns, x_mm, y_mm, z_mm, dx_mm, dy_mm, dz_mm,
                             sigma_x_mm, sigma_y_mm, sigma_z_mm, views, reproj_px)
    SELECT ins.test_id, ins.seq, (t->>'id')::int, ins.t_ns,
           (t->'pos_mm'->>0)::float8, (t->'pos_mm'->>1)::float8, (t->'pos_mm'->>2)::float8,
           (t->'disp_mm'->>0)::float8, (t->'disp_mm'->>1)::float8, (t->'disp_mm'->>2)::float8,
           (t->'sigma_mm'->>0)::float8, (t->'sigma_mm'->>1)::float8, (t->'sigma_mm'->>2)::float8,
           (t->>'views')::int, (t->>'reproj_px')::float8
    FROM ins CROSS JOIN LATERAL jsonb_array_elements(ins.line->'tags') AS t
    RETURNING 1
), gauges AS (
    INSERT INTO gauge_samples (test_id, seq, name, t_ns, value, sigma, unit)
    SELECT ins.test_id, ins.seq, g.key, ins.t_ns, (g.value->>'value')::float8, (g.value->>'sigma')::float8, g.value->>'unit'
    FROM ins CROSS JOIN LATERAL jsonb_each(
        CASE WHEN jsonb_typeof(ins.line->'gauges') = 'object' THEN ins.line->'gauges' ELSE '{}'::jsonb END) AS g
    RETURNING 1
)
SELECT (SELECT count(*) FROM ins), (SELECT count(*) FROM tags), (SELECT count(*) FROM gauges)
"#;

/// True for errors that say the data is bad (SQLSTATE classes 22 and 23), as opposed to
/// the connection or the server going away.
pub fn is_data_error(e: &tokio_postgres::Error) -> bool {
    e.code().is_some_and(|c| c.code().starts_with("22") || c.code().starts_with("23"))
}

impl Db {
    /// Connects, applies the migrations that are missing and prepares the statements.
    pub async fn connect(url: &str) -> Result<Db, tokio_postgres::Error> {
        let (mut client, connection) = tokio_postgres::connect(url, NoTls).await?;
        let conn = tokio::spawn(async move {
            if let Err(e) = connection.await {
                tracing::debug!("PostgreSQL connection closed: {e}");
            }
        });
        migrate(&mut client).await?;
        let insert = client.prepare(INSERT_SQL).await?;
        Ok(Db { client, conn, insert, tests: HashMap::new() })
    }

    /// True once the connection has gone (the server stopped, the network broke).
    pub fn is_closed(&self) -> bool {
        self.client.is_closed()
    }

    /// Writes one batch in one transaction: rigs and tests as needed, every feed line
    /// upserted on (rig, test, seq) with its tag and gauge samples, the latest status per
    /// test. Nothing is written unless everything is.
    pub async fn write(&mut self, lines: &[LineRow], statuses: &[StatusRow]) -> Result<Written, tokio_postgres::Error> {
        let tx = self.client.transaction().await?;
        let mut new_ids = Vec::new();
        let mut ids: HashMap<(String, String), i64> = HashMap::new();
        for (rig, test) in lines.iter().map(|l| (&l.rig, &l.test)).chain(statuses.iter().map(|s| (&s.rig, &s.test))) {
            let key = (rig.clone(), test.clone());
            if ids.contains_key(&key) {
                continue;
            }
            let id = match self.tests.get(&key) {
                Some(id) => *id,
                None => {
                    let rig_id: i32 = tx
                        .query_one(
                            "INSERT INTO rigs (name) VALUES ($1) ON CONFLICT (name) DO UPDATE SET name = EXCLUDED.name RETURNING id",
                            &[rig],
                        )
                        .await?
                        .get(0);
                    let id: i64 = tx
                        .query_one(
                            "INSERT INTO tests (rig_id, name) VALUES ($1, $2) ON CONFLICT (rig_id, name) DO UPDATE SET name = EXCLUDED.name RETURNING id",
                            &[&rig_id, test],
                        )
                        .await?
                        .get(0);
                    new_ids.push((key.clone(), id));
                    id
                }
            };
            ids.insert(key, id);
        }
        let mut w = Written::default();
        if !lines.is_empty() {
            let test_ids: Vec<i64> = lines.iter().map(|l| ids[&(l.rig.clone(), l.test.clone())]).collect();
            let seqs: Vec<i64> = lines.iter().map(|l| l.seq).collect();
            let jsons: Vec<&serde_json::Value> = lines.iter().map(|l| &l.line).collect();
            let row = tx.query_one(&self.insert, &[&test_ids, &seqs, &jsons]).await?;
            let inserted: i64 = row.get(0);
            w.inserted = inserted as u64;
            w.duplicates = lines.len() as u64 - w.inserted;
            w.tags = row.get::<_, i64>(1) as u64;
            w.gauges = row.get::<_, i64>(2) as u64;
        }
        for s in statuses {
            let id = ids[&(s.rig.clone(), s.test.clone())];
            tx.execute("UPDATE tests SET status = $2, status_at = now() WHERE id = $1", &[&id, &s.status]).await?;
            tx.execute(
                "UPDATE rigs SET status = $2, status_at = now() WHERE id = (SELECT rig_id FROM tests WHERE id = $1)",
                &[&id, &s.status],
            )
            .await?;
        }
        tx.commit().await?;
        self.tests.extend(new_ids);
        Ok(w)
    }

    /// Writes a batch; when the database refuses it as bad data, writes the rows one by one
    /// and skips (logs) those it refuses, so one bad line never stalls the archive.
    pub async fn write_or_skip(&mut self, lines: &[LineRow], statuses: &[StatusRow]) -> Result<Written, tokio_postgres::Error> {
        match self.write(lines, statuses).await {
            Err(e) if is_data_error(&e) => {
                tracing::warn!("archive: the database refused a batch ({e}); writing its lines one by one");
                let mut total = Written::default();
                for l in lines {
                    match self.write(std::slice::from_ref(l), &[]).await {
                        Ok(w) => {
                            total.inserted += w.inserted;
                            total.duplicates += w.duplicates;
                            total.tags += w.tags;
                            total.gauges += w.gauges;
                        }
                        Err(e) if is_data_error(&e) => {
                            tracing::warn!(rig = %l.rig, test = %l.test, seq = l.seq, "archive: feed line skipped, the database refused it: {e}");
                            total.rejected += 1;
                        }
                        Err(e) => return Err(e),
                    }
                }
                for s in statuses {
                    match self.write(&[], std::slice::from_ref(s)).await {
                        Ok(_) => {}
                        Err(e) if is_data_error(&e) => total.rejected += 1,
                        Err(e) => return Err(e),
                    }
                }
                Ok(total)
            }
            other => other,
        }
    }
}

impl Drop for Db {
    fn drop(&mut self) {
        self.conn.abort();
    }
}

/// Applies the missing migrations in one transaction under an advisory lock (several
/// archives may start at once). A database newer than this program is used as it is.
pub async fn migrate(client: &mut Client) -> Result<(), tokio_postgres::Error> {
    let tx = client.transaction().await?;
    tx.execute("SELECT pg_advisory_xact_lock($1)", &[&MIGRATION_LOCK]).await?;
    tx.batch_execute(
        "CREATE TABLE IF NOT EXISTS tagdeflect_migrations (
            version integer PRIMARY KEY, name text NOT NULL, applied_at timestamptz NOT NULL DEFAULT now())",
    )
    .await?;
    let current: i32 = tx.query_one("SELECT coalesce(max(version), 0) FROM tagdeflect_migrations", &[]).await?.get(0);
    let newest = MIGRATIONS.last().map_or(0, |m| m.0);
    if current > newest {
        tracing::warn!(
            "archive: the database schema is at version {current}, newer than this program's {newest}; going on (migrations only add)"
        );
    }
    for (version, name, sql) in MIGRATIONS {
        if *version <= current {
            continue;
        }
        tracing::info!(version, name, "archive: applying schema migration");
        tx.batch_execute(sql).await?;
        tx.execute("INSERT INTO tagdeflect_migrations (version, name) VALUES ($1, $2)", &[version, name]).await?;
    }
    tx.commit().await
}
