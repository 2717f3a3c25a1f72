//! The archive's PostgreSQL side: the connection and the batched upsert of feed lines, status
//! messages and lab tests in one transaction. The schema's migrations are in `migrate`, the
//! rows in `rows`, what the archive holds of every test (runs, held seqs) in `holdings`, which
//! version of a lab test's record is kept in `versions`.

mod batch;
mod holdings;
mod migrate;
mod rows;
mod versions;

use std::collections::HashMap;

use tokio_postgres::{Client, NoTls, Statement};

pub use holdings::Holdings;
use holdings::{load_holdings, log_gaps};
pub use migrate::{migrate, MIGRATIONS};
pub use rows::{LabTestRow, LineKey, LineRow, NewRun, StatusRow, Written};

/// A connection to the archive database.
pub struct Db {
    client: Client,
    conn: tokio::task::JoinHandle<()>,
    insert: Statement,
    tests: HashMap<(String, String), i64>,
    holdings: HashMap<i64, Holdings>,
    /// Other archives write too (`--group`): read the holdings afresh for every batch.
    shared: bool,
}

const INSERT_SQL: &str = r#"
WITH src AS (
    SELECT * FROM unnest($1::bigint[], $2::int[], $3::bigint[], $4::jsonb[]) AS s(test_id, run, seq, line)
), ins AS (
    INSERT INTO frame_sets (test_id, run, seq, t_ns, load_kn, stroke_mm, net_deflection_mm, reproj_px, line)
    SELECT test_id, run, seq, (line->>'t_ns')::bigint, (line->>'load_kN')::float8, (line->>'stroke_mm')::float8,
           (line->>'net_deflection_mm')::float8, (line->>'reproj_px')::float8, line
    FROM src
    ON CONFLICT (test_id, run, seq) DO NOTHING
    RETURNING test_id, run, seq, t_ns, line
), tags AS (
    INSERT INTO tag_samples (test_id, run, seq, tag_id, t_ns, x_mm, y_mm, z_mm, dx_mm, dy_mm, dz_mm,
                             sigma_x_mm, sigma_y_mm, sigma_z_mm, views, reproj_px)
    SELECT ins.test_id, ins.run, ins.seq, (t->>'id')::int, ins.t_ns,
           (t->'pos_mm'->>0)::float8, (t->'pos_mm'->>1)::float8, (t->'pos_mm'->>2)::float8,
           (t->'disp_mm'->>0)::float8, (t->'disp_mm'->>1)::float8, (t->'disp_mm'->>2)::float8,
           (t->'sigma_mm'->>0)::float8, (t->'sigma_mm'->>1)::float8, (t->'sigma_mm'->>2)::float8,
           (t->>'views')::int, (t->>'reproj_px')::float8
    FROM ins CROSS JOIN LATERAL jsonb_array_elements(ins.line->'tags') AS t
    RETURNING 1
), gauges AS (
    INSERT INTO gauge_samples (test_id, run, seq, name, t_ns, value, sigma, unit)
    SELECT ins.test_id, ins.run, ins.seq, g.key, ins.t_ns, (g.value->>'value')::float8, (g.value->>'sigma')::float8, g.value->>'unit'
    FROM ins CROSS JOIN LATERAL jsonb_each(
        CASE WHEN jsonb_typeof(ins.line->'gauges') = 'object' THEN ins.line->'gauges' ELSE '{}'::jsonb END) AS g
    RETURNING 1
)
SELECT (SELECT count(*) FROM tags), (SELECT count(*) FROM gauges),
       (SELECT coalesce(array_agg(test_id), '{}') FROM ins), (SELECT coalesce(array_agg(run), '{}') FROM ins),
       (SELECT coalesce(array_agg(seq), '{}') FROM ins)
"#;

/// True for errors that say the data is bad (SQLSTATE classes 22 and 23), as opposed to
/// the connection or the server going away.
pub fn is_data_error(e: &tokio_postgres::Error) -> bool {
    e.code().is_some_and(|c| c.code().starts_with("22") || c.code().starts_with("23"))
}

impl Db {
    /// Connects, applies the migrations that are missing and prepares the statements.
    /// `shared`: other archives write to the same tests (`--group`), so what is held is
    /// read afresh for every batch.
    pub async fn connect(url: &str, shared: bool) -> Result<Db, tokio_postgres::Error> {
        let (mut client, connection) = tokio_postgres::connect(url, NoTls).await?;
        let conn = tokio::spawn(async move {
            if let Err(e) = connection.await {
                tracing::debug!("PostgreSQL connection closed: {e}");
            }
        });
        migrate(&mut client).await?;
        let insert = client.prepare(INSERT_SQL).await?;
        Ok(Db { client, conn, insert, tests: HashMap::new(), holdings: HashMap::new(), shared })
    }

    /// True once the connection has gone (the server stopped, the network broke).
    pub fn is_closed(&self) -> bool {
        self.client.is_closed()
    }

    /// What this archive holds of a test (as of its last commit touching it).
    pub fn holdings(&self, test_id: i64) -> Option<&Holdings> {
        self.holdings.get(&test_id)
    }

    /// Writes one batch in one transaction: rigs and tests as needed, every feed line
    /// upserted on (rig, test, run, seq) with its tag and gauge samples, the latest status
    /// per test. Nothing is written unless everything is. Logs the runs it begins and the
    /// gaps that open and close.
    pub async fn write(
        &mut self,
        lines: &[LineRow],
        statuses: &[StatusRow],
        labs: &[LabTestRow],
    ) -> Result<Written, tokio_postgres::Error> {
        let tx = self.client.transaction().await?;
        let mut w = Written::default();
        let (ids, new_ids) = batch::test_ids(&tx, &self.tests, lines, statuses, labs, &mut w).await?;
        // What is held of every test the lines go to, and the run of every line.
        let mut old: HashMap<i64, Holdings> = HashMap::new();
        let mut work: HashMap<i64, Holdings> = HashMap::new();
        for (_, _, id) in &w.touched {
            let h = match (self.shared, self.holdings.get(id)) {
                (false, Some(h)) => h.clone(),
                _ => load_holdings(&tx, *id).await?,
            };
            old.insert(*id, h.clone());
            work.insert(*id, h);
        }
        let mut new_runs: Vec<NewRun> = Vec::new();
        if !lines.is_empty() {
            batch::insert_lines(&tx, &self.insert, lines, &ids, &mut work, &mut new_runs, &mut w).await?;
        }
        batch::write_statuses(&tx, statuses, &ids).await?;
        let (lab_tests, refused) = batch::write_lab_tests(&tx, labs, &ids).await?;
        w.lab_tests += lab_tests;
        tx.commit().await?;
        self.tests.extend(new_ids);
        batch::log_new_runs(&new_runs);
        batch::log_refused(&refused);
        for (rig, test, id) in &w.touched {
            if let (Some(before), Some(after)) = (old.get(id), work.get(id)) {
                log_gaps(rig, test, before, after);
            }
        }
        self.holdings.extend(work);
        Ok(w)
    }

    /// Writes a batch; when the database refuses it as bad data, writes the rows one by one
    /// and skips (logs) those it refuses, so one bad line never stalls the archive.
    pub async fn write_or_skip(
        &mut self,
        lines: &[LineRow],
        statuses: &[StatusRow],
        labs: &[LabTestRow],
    ) -> Result<Written, tokio_postgres::Error> {
        match self.write(lines, statuses, labs).await {
            Err(e) if is_data_error(&e) => {
                tracing::warn!("archive: the database refused a batch ({}); writing its lines one by one", crate::chain(&e));
                let mut total = Written::default();
                for l in lines {
                    match self.write(std::slice::from_ref(l), &[], &[]).await {
                        Ok(w) => total.add(w),
                        Err(e) if is_data_error(&e) => {
                            tracing::warn!(rig = %l.rig, test = %l.test, seq = l.seq, "archive: feed line skipped, the database refused it: {}", crate::chain(&e));
                            total.rejected += 1;
                        }
                        Err(e) => return Err(e),
                    }
                }
                for s in statuses {
                    match self.write(&[], std::slice::from_ref(s), &[]).await {
                        Ok(_) => {}
                        Err(e) if is_data_error(&e) => total.rejected += 1,
                        Err(e) => return Err(e),
                    }
                }
                for l in labs {
                    match self.write(&[], &[], std::slice::from_ref(l)).await {
                        Ok(w) => total.add(w),
                        Err(e) if is_data_error(&e) => {
                            tracing::warn!(rig = %l.rig, test = %l.message.record.id, "archive: lab test record skipped, the database refused it: {}", crate::chain(&e));
                            total.rejected += 1;
                        }
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
