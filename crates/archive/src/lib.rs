//! `tagdeflect archive --mqtt URL --postgres URL` (SPEC "Archive"): subscribes to the
//! feeds that rigs publish (`[output.mqtt]`) and keeps every line in PostgreSQL.
//!
//! ```text
//! broker ──<topic>/feed──▶ MQTT task ──▶ writer: batch ─▶ one transaction ─▶ PUBACKs
//! ```
//!
//! - **At least once, never twice.** The session is persistent (`clean_session = false`,
//!   a fixed client id) and acknowledgements are manual: a message is acknowledged only
//!   after the transaction holding it has committed. Whatever was received but not
//!   committed when the archive, the broker or the database went away is redelivered by
//!   the broker; rows are upserted on (rig, test, seq), so a redelivery never makes a
//!   duplicate.
//! - **Batches** form by themselves: while one transaction commits, the next messages
//!   queue up and go into the next one (up to `--batch` lines).
//! - **Several archives** can share the load (`--group NAME`): they subscribe to the same
//!   MQTT shared subscription `$share/<group>/...` (each with its own `--client-id`), so
//!   the broker hands each message to one of them. One archive alone uses a plain
//!   persistent subscription: Mosquitto 2.0 restores those after its own restart, not
//!   shared ones (lines published between the broker's restart and the archives'
//!   reconnection would be lost to a shared group).
//! - **Bad messages** (not JSON, not a feed line, a topic that does not fit the template)
//!   are logged, acknowledged and skipped; the database refusing a row as bad data skips
//!   that row only.
//! - **Outages**: the MQTT connection and the database connection are retried with a
//!   backoff (0.2 s doubling to 2 s); while the database is away nothing is acknowledged
//!   and the broker holds the backlog.
//!
//! Errors are [`ArchiveError`]s, which tell bad input from runtime failures.
//!
//! The files: [`options`](ArchiveOptions) (the command line and its checks), `service` (the
//! connections, retries and the stop), `writer` (batches, transactions, acknowledgements),
//! `message` (one message checked against its topic, [`check_message`]), `db` (the schema
//! and the upserts), [`backfill`], [`bench`], [`local`] (local servers for tests), `fuzz`.
//! What crosses the broker (topics, the acknowledgement, the lab test's record) is the wire
//! contract, `tagdeflect_wire`, shared with the rigs' publisher.

pub mod backfill;
pub mod bench;
mod db;
mod error;
mod fuzz;
pub mod local;
mod message;
mod options;
mod service;
mod writer;

pub use error::ArchiveError;
pub use fuzz::fuzz_message;
pub use message::{check_message, Malformed, MAX_MESSAGE_BYTES};
pub use options::{ArchiveCommand, ArchiveOptions};
pub use service::{chain, run};
