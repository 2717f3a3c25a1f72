//! A test as a lab runs it (SPEC "Tests"): one specimen from start to stop, while the daemon
//! keeps measuring between tests.
//!
//! ```text
//! control API / `tagdeflect test` ──start/stop/mark/zero──▶ LabTests (one lock, short holds)
//! solver thread ──LabTests::apply(&mut line)──▶ the line gets `test`, `events`, values from the zero
//! sinks' thread ──LabTests::on_line──▶ tests/<id>/feed.jsonl
//! UTM forwarder ──LabTests::on_utm──▶ tests/<id>/utm.jsonl (every sample, at its own rate)
//! ```
//!
//! States: idle → running → idle. `start` opens `tests/<id>/` (id: the UTC start time and the
//! specimen, `20261202T013000Z-B12`); the test's zero is the mean of its first
//! [`ZERO_SETS`] frame sets — per specimen tag (its position), the net deflection and each
//! gauge — and every later value counts from it (lines taken while the zero forms are marked
//! `zeroing` and count from the mean so far; the zero's σ, the spread of those sets over √n,
//! goes into every σ). `zero` takes it again from the next sets. `mark` puts an operator's
//! note into the feed and `test.json`. A test's feed holds its own lines only: none exposed
//! before its start; `stop` puts its event on the next line — the test's last — and waits (at
//! most [`STOP_WAIT`]) until the sinks have written it, then completes the folder: `tagdeflect.toml` (the
//! config in force), `test.json` (metadata, events, the SHA-256 of every file of the folder
//! and of the calibration files) and, through the hook the binary installs, `report/`.
//!
//! A running test survives a restart of the daemon (a crash, `Restart=on-failure`): its state —
//! the record, the folder, the zero with its σ — is kept in `TESTS/.running.json` (written at
//! start, when the zero forms and at every event, atomically); a daemon that finds it at start
//! resumes the test from the same zero and puts a `resume` event (with the gap) into the feed
//! and `test.json`, so the curve never gets a second zero in its middle. The new daemon numbers
//! its frame sets from 0 again (a feed line's `seq` is the daemon's frame-set count, not the
//! test's), so the test's `feed.jsonl` has `seq` going back at the line with the `resume`
//! event: that line starts a new segment of the same test, which the report's feed reader
//! (`tagdeflect_report`) reads as one test across it, the hole a gap in time;
//! a `seq` going back on a line without the event stays an error there.
//!
//! Tests may also start and stop by themselves, from the load and the standard's end
//! (`[output.auto_test]`, [`auto`]); an automatic stop runs on a short thread of its own, as
//! `stop` waits for the sinks.
//!
//! Nothing here blocks the solver for longer than a few field updates under the lock: files are
//! written on the sinks' thread and by the caller of `stop`.
//!
//! Files by job: [`meta`] what a test is started with, [`record`] `test.json` and the earlier
//! tests' curves, `state` the tests and their lock, `commands` what an operator does,
//! `steps` what the pipeline's threads do, `folder` the files on disk, `stopping` a stop that
//! survives a crash, `zero` the test's zero, [`audit`] the audit log, sign-off and re-analysis,
//! `start` a start with its method and specimen (refused when its report could not be made),
//! [`specimens`] the table entered beforehand, `crack` the operator's crack entry.

pub mod audit;
pub mod auto;
mod commands;
mod crack;
mod folder;
pub mod frames;
pub mod meta;
mod preload;
pub mod record;
pub mod specimens;
mod start;
mod state;
mod steps;
mod stopping;
mod verification;
mod zero;

#[cfg(test)]
mod tests;
#[cfg(test)]
mod tests_auto_start;
#[cfg(test)]
mod tests_method;
#[cfg(test)]
mod tests_stop;

pub use commands::{START_RETRY_AFTER_S, START_WAIT, STOP_WAIT};
pub use crack::CrackRequest;
pub use meta::{TestError, TestMeta, STANDARDS};
pub use record::{EarlierTest, Stopped, TestRecord, EARLIER_POINTS, EARLIER_TESTS};
pub use specimens::parse_specimens;
pub use start::{standard_requires, NEXT};
pub use state::{FolderHook, LabTests, RecordHook, ReportError, ReportHook};
pub use steps::LabTestSink;
pub use verification::VerificationCheck;
pub use zero::ZERO_SETS;
