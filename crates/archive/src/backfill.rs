//! `tagdeflect archive backfill FEED --rig R --test T --postgres URL`: loads a rig's feed
//! file (or a test folder holding `feed.jsonl`) into the archive, idempotently, for rigs
//! that were away from the broker for longer than their buffer (or whose archive was).
//!
//! The lines go through the same checks and the same writer as the ones from MQTT: a line
//! the archive already holds (same rig, test, seq and `t_ns`) is left as it is, a line with
//! a seq held with another `t_ns` goes to its own run. Every line is read and checked
//! before anything is written; a line that is not a feed line stops the backfill with its
//! file and line (exit 2), except a partial last line (a rig stopped mid-write), which is
//! skipped with a warning. With `--mqtt`, the archive's acknowledgement of the test is
//! published afterwards, so a rig still running learns what the archive now holds.

use std::path::{Path, PathBuf};
use std::time::Duration;

use rumqttc::{AsyncClient, Event, Packet, QoS};

use crate::db::{Db, LineRow};
use crate::message::{parse_message, Parsed};
use crate::ArchiveError;
use tagdeflect_wire::TopicLayout;

/// Options of `tagdeflect archive backfill`.
#[derive(Debug, Clone)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct BackfillOptions {
    /// The feed file (JSON lines), or a folder holding `feed.jsonl` (a `[report]` run folder).
    pub feed: PathBuf,
    /// The rig's name, as in its `[output.mqtt] rig`.
    #[cfg_attr(feature = "clap", arg(long))]
    pub rig: String,
    /// The test id, as the rig published it.
    #[cfg_attr(feature = "clap", arg(long))]
    pub test: String,
    /// The database (as for `tagdeflect archive`).
    #[cfg_attr(feature = "clap", arg(long))]
    pub postgres: String,
    /// Also publish the archive's acknowledgement of the test to this broker.
    #[cfg_attr(feature = "clap", arg(long))]
    pub mqtt: Option<String>,
    /// The rigs' topic template (with --mqtt).
    #[cfg_attr(feature = "clap", arg(long, default_value = "tagdeflect/{rig}/{test}"))]
    pub topic: String,
}

/// What a backfill did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct BackfillSummary {
    /// Feed lines read from the file.
    pub read: u64,
    /// Lines newly stored.
    pub inserted: u64,
    /// Lines the archive held already.
    pub duplicates: u64,
}

/// Reads and checks every line of a feed (bad input names the file and line): a feed file, a
/// test folder's `feed.jsonl`, or a rotated run's current file — then its rotated files are
/// read first, in order ([`tagdeflect_core::feed_rotation::feed_files`]).
pub fn read_feed(path: &Path, rig: &str, test: &str) -> Result<Vec<LineRow>, ArchiveError> {
    let file = if path.is_dir() { path.join("feed.jsonl") } else { path.to_path_buf() };
    let files =
        tagdeflect_core::feed_rotation::feed_files(&file).map_err(|e| ArchiveError::BadOption(format!("{}: {e}", file.display())))?;
    if files.is_empty() {
        return Err(ArchiveError::BadOption(format!("{}: no such file", file.display())));
    }
    let mut out = Vec::new();
    for f in &files {
        read_one(f, rig, test, &mut out)?;
    }
    Ok(out)
}

/// [`read_feed`] of one file.
fn read_one(file: &Path, rig: &str, test: &str, out: &mut Vec<LineRow>) -> Result<(), ArchiveError> {
    let text = std::fs::read(file).map_err(|e| ArchiveError::BadOption(format!("{}: {e}", file.display())))?;
    let layout = TopicLayout::new("b/{rig}/{test}").expect("a valid template");
    let topic = format!("b/{rig}/{test}/feed");
    let complete = text.last() == Some(&b'\n');
    let lines: Vec<&[u8]> = text.split(|b| *b == b'\n').collect();
    let n = lines.len();
    for (i, raw) in lines.into_iter().enumerate() {
        if raw.iter().all(u8::is_ascii_whitespace) {
            continue;
        }
        match parse_message(&layout, &topic, raw) {
            Ok(Parsed::Line(l)) => out.push(l),
            Ok(_) => unreachable!("a feed topic"),
            Err(why) if i + 1 == n && !complete => {
                tracing::warn!("{}:{}: partial last line skipped ({why})", file.display(), i + 1);
            }
            Err(why) => return Err(ArchiveError::BadOption(format!("{}:{}: {why}", file.display(), i + 1))),
        }
    }
    Ok(())
}

/// Runs a backfill and prints what it did.
pub fn run(opts: &BackfillOptions) -> Result<(), ArchiveError> {
    tagdeflect_wire::check_level_name("--rig", &opts.rig).map_err(|m| ArchiveError::BadOption(m.to_string()))?;
    tagdeflect_wire::check_level_name("--test", &opts.test).map_err(|m| ArchiveError::BadOption(m.to_string()))?;
    let layout = TopicLayout::new(&opts.topic).map_err(|m| ArchiveError::BadOption(format!("--topic: {m}")))?;
    if let Some(m) = &opts.mqtt {
        tagdeflect_wire::BrokerUrl::parse(m).map_err(|m| ArchiveError::BadOption(format!("--mqtt: {m}")))?;
    }
    let _: tokio_postgres::Config =
        opts.postgres.parse().map_err(|e| ArchiveError::BadOption(format!("--postgres \"{}\": {e}", opts.postgres)))?;
    let lines = read_feed(&opts.feed, &opts.rig, &opts.test)?;
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().map_err(ArchiveError::Runtime)?;
    let s = rt.block_on(async {
        let mut db = Db::connect(&opts.postgres, true).await.map_err(|e| ArchiveError::Database(crate::chain(&e)))?;
        let mut sum = BackfillSummary { read: lines.len() as u64, ..BackfillSummary::default() };
        let mut test_id = None;
        for chunk in lines.chunks(1000) {
            let w = db.write_or_skip(chunk, &[], &[]).await.map_err(|e| ArchiveError::Database(crate::chain(&e)))?;
            sum.inserted += w.inserted;
            sum.duplicates += w.duplicates;
            test_id = test_id.or(w.touched.first().map(|t| t.2));
        }
        if let (Some(url), Some(id)) = (&opts.mqtt, test_id) {
            let runs = db.holdings(id).map(|h| h.ack_runs()).unwrap_or_default();
            let ack = tagdeflect_wire::ArchiveAck {
                rig: opts.rig.clone(),
                test: opts.test.clone(),
                runs,
                at_ns: tagdeflect_core::clock::now_epoch_ns(),
            };
            let topic = format!("{}/{}", layout.topic_of(&opts.rig, &opts.test), tagdeflect_wire::ACK_SUFFIX);
            publish_once(url, &topic, serde_json::to_vec(&ack).expect("ack serialises")).await?;
        }
        Ok::<_, ArchiveError>(sum)
    })?;
    println!(
        "backfill: {} feed lines of rig {} test {} read from {}: {} stored, {} already held",
        s.read,
        opts.rig,
        opts.test,
        opts.feed.display(),
        s.inserted,
        s.duplicates
    );
    Ok(())
}

/// Publishes one retained message at QoS 1 and waits for the broker's acknowledgement.
async fn publish_once(url: &str, topic: &str, payload: Vec<u8>) -> Result<(), ArchiveError> {
    let id = format!("tagdeflect-backfill-{:08x}", rand::random::<u32>());
    let mo = tagdeflect_wire::mqtt_options(url, &id, None, None, None).map_err(|m| ArchiveError::BadOption(m.to_string()))?;
    let (client, mut el) = AsyncClient::new(mo, 4);
    client.publish(topic, QoS::AtLeastOnce, true, payload).await?;
    let wait = async {
        loop {
            match el.poll().await {
                Ok(Event::Incoming(Packet::PubAck(_))) => return Ok(()),
                Ok(_) => {}
                Err(e) => return Err(ArchiveError::Database(format!("broker {url}: {e}"))),
            }
        }
    };
    let r = tokio::time::timeout(Duration::from_secs(10), wait)
        .await
        .unwrap_or_else(|_| Err(ArchiveError::Database(format!("broker {url}: no acknowledgement within 10 s"))));
    let _ = client.try_disconnect();
    r
}
