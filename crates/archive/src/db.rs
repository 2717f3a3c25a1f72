//! The archive's PostgreSQL side: the connection and the batched upsert of feed lines, status
//! messages and lab tests in one transaction. The schema's migrations are in `migrate`, the
//! rows in `rows`, what the archive holds of every test (runs, held seqs) in `holdings`.

mod holdings;
mod migrate;
mod rows;

use std::collections::HashMap;

use tokio_postgres::{Client, NoTls, Statement};

pub use holdings::Holdings;
use holdings::{load_holdings, log_gaps};
pub use migrate::{migrate, MIGRATIONS};
pub use rows::{LabTestRow, LineKey, LineRow, NewRun, StatusRow, Written};

/// Upserts a lab test; a record with fewer events than the one held is an older version
/// (a redelivery after a newer one) and leaves it as it is.
const LAB_TEST_SQL: &str = r#"
INSERT INTO lab_tests (rig_id, id, run_test_id, specimen, operator, standard, notes, measured,
                       started_t_ns, stopped_t_ns, events, sha256, record)
VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10, $11, $12, $13)
ON CONFLICT (rig_id, id) DO UPDATE SET
    run_test_id = EXCLUDED.run_test_id, specimen = EXCLUDED.specimen, operator = EXCLUDED.operator,
    standard = EXCLUDED.standard, notes = EXCLUDED.notes, measured = EXCLUDED.measured,
    started_t_ns = EXCLUDED.started_t_ns, stopped_t_ns = EXCLUDED.stopped_t_ns, events = EXCLUDED.events,
    sha256 = EXCLUDED.sha256, record = EXCLUDED.record, updated_at = now()
WHERE jsonb_array_length(EXCLUDED.events) >= jsonb_array_length(lab_tests.events)
"#;

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
        let mut new_ids = Vec::new();
        let mut ids: HashMap<(String, String), i64> = HashMap::new();
        let mut w = Written::default();
        for (rig, test) in lines
            .iter()
            .map(|l| (&l.rig, &l.test))
            .chain(statuses.iter().map(|s| (&s.rig, &s.test)))
            .chain(labs.iter().map(|l| (&l.rig, &l.run)))
        {
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
            ids.insert(key.clone(), id);
            if lines.iter().any(|l| l.rig == key.0 && l.test == key.1) {
                w.touched.push((key.0, key.1, id));
            }
        }
        // What is held of every test the lines go to, and the run of every line.
        let mut work: HashMap<i64, Holdings> = HashMap::new();
        let mut old: HashMap<i64, Holdings> = HashMap::new();
        for (_, _, id) in &w.touched {
            let h = match (self.shared, self.holdings.get(id)) {
                (false, Some(h)) => h.clone(),
                _ => load_holdings(&tx, *id).await?,
            };
            old.insert(*id, h.clone());
            work.insert(*id, h);
        }
        let mut new_runs: Vec<NewRun> = Vec::new();
        let mut keys: Vec<LineKey> = Vec::with_capacity(lines.len());
        for l in lines {
            let id = ids[&(l.rig.clone(), l.test.clone())];
            let h = work.get_mut(&id).expect("loaded");
            let (run, new) = h.assign(l.seq as u64, l.t_ns);
            if new && run > 1 {
                new_runs.push(NewRun { rig: l.rig.clone(), test: l.test.clone(), run, seq: l.seq });
            }
            keys.push(LineKey { test_id: id, run, seq: l.seq });
        }
        if !lines.is_empty() {
            let inserted = insert_rows(&tx, &self.insert, lines, &keys, &mut w).await?;
            // Lines not inserted: a redelivery (same t_ns), or a line of another run that
            // fell into this run's span (a different t_ns): that one goes to a new run.
            let missed: Vec<usize> = (0..lines.len()).filter(|i| !inserted.contains(&keys[*i])).collect();
            let mut again: Vec<usize> = Vec::new();
            if !missed.is_empty() {
                let t_ids: Vec<i64> = missed.iter().map(|&i| keys[i].test_id).collect();
                let runs: Vec<i32> = missed.iter().map(|&i| keys[i].run).collect();
                let seqs: Vec<i64> = missed.iter().map(|&i| keys[i].seq).collect();
                let rows = tx
                    .query(
                        "SELECT f.test_id, f.run, f.seq, f.t_ns FROM frame_sets f
                         JOIN unnest($1::bigint[], $2::int[], $3::bigint[]) AS k(test_id, run, seq)
                           ON f.test_id = k.test_id AND f.run = k.run AND f.seq = k.seq",
                        &[&t_ids, &runs, &seqs],
                    )
                    .await?;
                let stored: HashMap<LineKey, i64> =
                    rows.iter().map(|r| (LineKey { test_id: r.get(0), run: r.get(1), seq: r.get(2) }, r.get::<_, i64>(3))).collect();
                let mut moved: HashMap<i64, i32> = HashMap::new();
                for i in missed {
                    if stored.get(&keys[i]).is_some_and(|t| *t != lines[i].t_ns) {
                        let h = work.get_mut(&keys[i].test_id).expect("loaded");
                        let run = match moved.get(&keys[i].test_id) {
                            Some(&r) if h.run(r).is_some_and(|x| !x.held.contains(lines[i].seq as u64)) => {
                                let x = h.runs.iter_mut().find(|x| x.run == r).expect("run");
                                x.held.insert(lines[i].seq as u64);
                                x.min_t = x.min_t.min(lines[i].t_ns);
                                x.max_t = x.max_t.max(lines[i].t_ns);
                                r
                            }
                            _ => {
                                let r = h.new_run(lines[i].seq as u64, lines[i].t_ns);
                                new_runs.push(NewRun { rig: lines[i].rig.clone(), test: lines[i].test.clone(), run: r, seq: lines[i].seq });
                                moved.insert(keys[i].test_id, r);
                                r
                            }
                        };
                        keys[i].run = run;
                        again.push(i);
                    } else {
                        w.duplicates += 1;
                    }
                }
            }
            if !again.is_empty() {
                let rows: Vec<LineRow> = again.iter().map(|&i| lines[i].clone()).collect();
                let k: Vec<LineKey> = again.iter().map(|&i| keys[i]).collect();
                let inserted = insert_rows(&tx, &self.insert, &rows, &k, &mut w).await?;
                w.duplicates += (rows.len() - inserted.len()) as u64;
            }
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
        for l in labs {
            let run_id = ids[&(l.rig.clone(), l.run.clone())];
            let r = &l.message.record;
            let json = |v: serde_json::Result<serde_json::Value>| v.unwrap_or(serde_json::Value::Null);
            let rig_id: i32 = tx.query_one("SELECT rig_id FROM tests WHERE id = $1", &[&run_id]).await?.get(0);
            tx.execute(
                LAB_TEST_SQL,
                &[
                    &rig_id,
                    &r.id,
                    &run_id,
                    &r.meta.specimen,
                    &r.meta.operator,
                    &r.meta.standard,
                    &r.meta.notes,
                    &json(serde_json::to_value(&r.meta.measured)),
                    &r.started_t_ns,
                    &r.stopped_t_ns,
                    &json(serde_json::to_value(&r.events)),
                    &json(serde_json::to_value(&r.sha256)),
                    &json(serde_json::to_value(&l.message)),
                ],
            )
            .await?;
            w.lab_tests += 1;
        }
        tx.commit().await?;
        self.tests.extend(new_ids);
        for r in &new_runs {
            tracing::warn!(
                rig = %r.rig, test = %r.test, run = r.run, seq = r.seq,
                "archive: seq {} of rig {} test {} arrived again with another t_ns: a new run {} (feed_lines shows it as test \"{}#{}\")",
                r.seq, r.rig, r.test, r.run, r.test, r.run
            );
        }
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

/// Inserts rows with their keys; returns the keys inserted (new).
async fn insert_rows(
    tx: &tokio_postgres::Transaction<'_>,
    insert: &Statement,
    lines: &[LineRow],
    keys: &[LineKey],
    w: &mut Written,
) -> Result<std::collections::HashSet<LineKey>, tokio_postgres::Error> {
    let test_ids: Vec<i64> = keys.iter().map(|k| k.test_id).collect();
    let runs: Vec<i32> = keys.iter().map(|k| k.run).collect();
    let seqs: Vec<i64> = keys.iter().map(|k| k.seq).collect();
    let jsons: Vec<&serde_json::Value> = lines.iter().map(|l| &l.line).collect();
    let row = tx.query_one(insert, &[&test_ids, &runs, &seqs, &jsons]).await?;
    w.tags += row.get::<_, i64>(0) as u64;
    w.gauges += row.get::<_, i64>(1) as u64;
    let (t, r, s): (Vec<i64>, Vec<i32>, Vec<i64>) = (row.get(2), row.get(3), row.get(4));
    w.inserted += t.len() as u64;
    Ok(t.into_iter().zip(r).zip(s).map(|((test_id, run), seq)| LineKey { test_id, run, seq }).collect())
}

impl Drop for Db {
    fn drop(&mut self) {
        self.conn.abort();
    }
}
