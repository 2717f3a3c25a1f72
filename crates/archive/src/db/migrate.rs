//! The schema: migrations applied on connect, versioned, idempotent, serialised between
//! several archives by an advisory lock.

use tokio_postgres::Client;

/// The schema migrations in order: (version, name, SQL). Files live in the workspace's
/// `migrations/`.
pub const MIGRATIONS: &[(i32, &str, &str)] = &[
    (1, "init", include_str!("../../../../migrations/0001_init.sql")),
    (2, "runs_and_gaps", include_str!("../../../../migrations/0002_runs_and_gaps.sql")),
    (3, "lab_tests", include_str!("../../../../migrations/0003_lab_tests.sql")),
];

/// Advisory lock key held while migrating ("tagdefle" in ASCII).
const MIGRATION_LOCK: i64 = 0x7461_6764_6566_6c65;

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
