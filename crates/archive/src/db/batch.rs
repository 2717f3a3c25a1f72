//! The steps of one batch's transaction ([`super::Db::write`]): the tests' row ids, the lines
//! inserted (a line that lands in another run's span goes to a new run), the statuses, the
//! lab tests (each version judged against the one held).

use std::collections::HashMap;

use tokio_postgres::{Error, Statement, Transaction};

use super::versions::{judge, Verdict};
use super::{Holdings, LabTestRow, LineKey, LineRow, NewRun, StatusRow, Written};

/// A lab test seen for the first time (two archives of a group may race: the second one
/// judges again against the first one's, [`super::versions`]).
const LAB_TEST_INSERT_SQL: &str = r#"
INSERT INTO lab_tests (rig_id, id, run_test_id, specimen, operator, standard, notes, measured,
                       started_t_ns, stopped_t_ns, events, sha256, record)
VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10, $11, $12, $13)
ON CONFLICT (rig_id, id) DO NOTHING
"#;

/// A lab test's newer version (judged by [`super::versions::judge`]).
const LAB_TEST_UPDATE_SQL: &str = r#"
UPDATE lab_tests SET
    run_test_id = $3, specimen = $4, operator = $5, standard = $6, notes = $7, measured = $8,
    started_t_ns = $9, stopped_t_ns = $10, events = $11, sha256 = $12, record = $13, updated_at = now()
WHERE rig_id = $1 AND id = $2
"#;

/// The row id of every (rig, test) of the batch — known ones from `known`, new ones inserted
/// (with their rig) and returned second, to be remembered after the commit; the tests that
/// lines go to are noted in `w.touched`.
pub(super) async fn test_ids(
    tx: &Transaction<'_>,
    known: &HashMap<(String, String), i64>,
    lines: &[LineRow],
    statuses: &[StatusRow],
    labs: &[LabTestRow],
    w: &mut Written,
) -> Result<(HashMap<(String, String), i64>, Vec<((String, String), i64)>), Error> {
    let mut new_ids = Vec::new();
    let mut ids: HashMap<(String, String), i64> = HashMap::new();
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
        let id = match known.get(&key) {
            Some(id) => *id,
            None => {
                let id = insert_test(tx, rig, test).await?;
                new_ids.push((key.clone(), id));
                id
            }
        };
        ids.insert(key.clone(), id);
        if lines.iter().any(|l| l.rig == key.0 && l.test == key.1) {
            w.touched.push((key.0, key.1, id));
        }
    }
    Ok((ids, new_ids))
}

/// The row id of a test (and its rig), inserted when new.
async fn insert_test(tx: &Transaction<'_>, rig: &String, test: &String) -> Result<i64, Error> {
    let rig_id: i32 = tx
        .query_one("INSERT INTO rigs (name) VALUES ($1) ON CONFLICT (name) DO UPDATE SET name = EXCLUDED.name RETURNING id", &[rig])
        .await?
        .get(0);
    Ok(tx
        .query_one(
            "INSERT INTO tests (rig_id, name) VALUES ($1, $2) ON CONFLICT (rig_id, name) DO UPDATE SET name = EXCLUDED.name RETURNING id",
            &[&rig_id, test],
        )
        .await?
        .get(0))
}

/// Inserts the batch's lines, each in the run `work` assigns it. Lines not inserted: a
/// redelivery (same t_ns, counted as a duplicate), or a line of another run that fell into
/// this run's span (a different t_ns): that one goes to a new run, noted in `new_runs`.
pub(super) async fn insert_lines(
    tx: &Transaction<'_>,
    insert: &Statement,
    lines: &[LineRow],
    ids: &HashMap<(String, String), i64>,
    work: &mut HashMap<i64, Holdings>,
    new_runs: &mut Vec<NewRun>,
    w: &mut Written,
) -> Result<(), Error> {
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
    let inserted = insert_rows(tx, insert, lines, &keys, w).await?;
    let missed: Vec<usize> = (0..lines.len()).filter(|i| !inserted.contains(&keys[*i])).collect();
    let again = if missed.is_empty() { Vec::new() } else { place_missed(tx, lines, &mut keys, &missed, work, new_runs, w).await? };
    if !again.is_empty() {
        let rows: Vec<LineRow> = again.iter().map(|&i| lines[i].clone()).collect();
        let k: Vec<LineKey> = again.iter().map(|&i| keys[i]).collect();
        let inserted = insert_rows(tx, insert, &rows, &k, w).await?;
        w.duplicates += (rows.len() - inserted.len()) as u64;
    }
    Ok(())
}

/// The lines not inserted: those stored with another t_ns move to a new run (one per test in
/// this batch; their `keys` updated) and are returned to be inserted again; the others are
/// duplicates.
async fn place_missed(
    tx: &Transaction<'_>,
    lines: &[LineRow],
    keys: &mut [LineKey],
    missed: &[usize],
    work: &mut HashMap<i64, Holdings>,
    new_runs: &mut Vec<NewRun>,
    w: &mut Written,
) -> Result<Vec<usize>, Error> {
    let stored = stored_t_ns(tx, keys, missed).await?;
    let mut again: Vec<usize> = Vec::new();
    let mut moved: HashMap<i64, i32> = HashMap::new();
    for &i in missed {
        if !stored.get(&keys[i]).is_some_and(|t| *t != lines[i].t_ns) {
            w.duplicates += 1;
            continue;
        }
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
    }
    Ok(again)
}

/// The t_ns stored under the keys of the `missed` lines.
async fn stored_t_ns(tx: &Transaction<'_>, keys: &[LineKey], missed: &[usize]) -> Result<HashMap<LineKey, i64>, Error> {
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
    Ok(rows.iter().map(|r| (LineKey { test_id: r.get(0), run: r.get(1), seq: r.get(2) }, r.get::<_, i64>(3))).collect())
}

/// Inserts rows with their keys; returns the keys inserted (new).
async fn insert_rows(
    tx: &Transaction<'_>,
    insert: &Statement,
    lines: &[LineRow],
    keys: &[LineKey],
    w: &mut Written,
) -> Result<std::collections::HashSet<LineKey>, Error> {
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

/// The status messages: each test's and its rig's status.
pub(super) async fn write_statuses(
    tx: &Transaction<'_>,
    statuses: &[StatusRow],
    ids: &HashMap<(String, String), i64>,
) -> Result<(), Error> {
    for s in statuses {
        let id = ids[&(s.rig.clone(), s.test.clone())];
        tx.execute("UPDATE tests SET status = $2, status_at = now() WHERE id = $1", &[&id, &s.status]).await?;
        tx.execute("UPDATE rigs SET status = $2, status_at = now() WHERE id = (SELECT rig_id FROM tests WHERE id = $1)", &[&id, &s.status])
            .await?;
    }
    Ok(())
}

/// A lab test version refused (logged after the commit).
pub(super) struct Refused {
    rig: String,
    id: String,
    why: String,
    older: bool,
}

/// The lab test records, each judged against the version held ([`super::versions`]) and
/// written when it is newer; how many were written, and the versions refused.
pub(super) async fn write_lab_tests(
    tx: &Transaction<'_>,
    labs: &[LabTestRow],
    ids: &HashMap<(String, String), i64>,
) -> Result<(u64, Vec<Refused>), Error> {
    let (mut written, mut refused) = (0u64, Vec::new());
    for l in labs {
        let run_id = ids[&(l.rig.clone(), l.run.clone())];
        let r = &l.message.record;
        let rig_id: i32 = tx.query_one("SELECT rig_id FROM tests WHERE id = $1", &[&run_id]).await?.get(0);
        // Twice at most: a row another archive inserted meanwhile is judged as held.
        for _ in 0..2 {
            let held: Option<serde_json::Value> = tx
                .query_opt("SELECT record FROM lab_tests WHERE rig_id = $1 AND id = $2 FOR UPDATE", &[&rig_id, &r.id])
                .await?
                .map(|row| row.get(0));
            // A held record this archive cannot read (an older schema's) is replaced.
            let held = held.and_then(|v| serde_json::from_value::<tagdeflect_wire::LabTestMessage>(v).ok());
            let verdict = held.as_ref().map_or(Verdict::Replace, |h| judge(&h.record, r));
            match verdict {
                Verdict::Same => break,
                Verdict::Refuse { why, older } => {
                    refused.push(Refused { rig: l.rig.clone(), id: r.id.clone(), why, older });
                    break;
                }
                Verdict::Replace => {
                    let sql = if held.is_some() { LAB_TEST_UPDATE_SQL } else { LAB_TEST_INSERT_SQL };
                    if upsert_lab_test(tx, sql, rig_id, run_id, l).await? == 1 {
                        written += 1;
                        break;
                    }
                }
            }
        }
    }
    Ok((written, refused))
}

/// One lab test row written by `sql` (insert or update); the rows it wrote.
async fn upsert_lab_test(tx: &Transaction<'_>, sql: &str, rig_id: i32, run_id: i64, l: &LabTestRow) -> Result<u64, Error> {
    let r = &l.message.record;
    let json = |v: serde_json::Result<serde_json::Value>| v.unwrap_or(serde_json::Value::Null);
    tx.execute(
        sql,
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
    .await
}

/// One line for every lab test version refused, naming the test and why.
pub(super) fn log_refused(refused: &[Refused]) {
    for r in refused {
        if r.older {
            tracing::info!(rig = %r.rig, test = %r.id, "archive: lab test {} of rig {}: version refused: {}", r.id, r.rig, r.why);
        } else {
            tracing::warn!(rig = %r.rig, test = %r.id, "archive: lab test {} of rig {}: version refused: {}", r.id, r.rig, r.why);
        }
    }
}

/// A warning for every line that started a new run (it arrived again with another t_ns).
pub(super) fn log_new_runs(new_runs: &[NewRun]) {
    for r in new_runs {
        tracing::warn!(
            rig = %r.rig, test = %r.test, run = r.run, seq = r.seq,
            "archive: seq {} of rig {} test {} arrived again with another t_ns: a new run {} (feed_lines shows it as test \"{}#{}\")",
            r.seq, r.rig, r.test, r.run, r.test, r.run
        );
    }
}
