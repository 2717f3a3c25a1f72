//! The command line of `tagdeflect archive` and its checks before anything connects.

use tagdeflect_wire::TopicLayout;

use crate::{backfill, ArchiveError};

/// Options of `tagdeflect archive`.
#[derive(Debug, Clone)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
#[cfg_attr(feature = "clap", command(subcommand_negates_reqs = true, args_conflicts_with_subcommands = true))]
pub struct ArchiveOptions {
    /// `backfill`: load a feed file into the archive instead of running it.
    #[cfg_attr(feature = "clap", command(subcommand))]
    pub command: Option<ArchiveCommand>,
    /// The broker: mqtt://[user[:password]@]host[:port] or mqtts://... (TLS).
    #[cfg_attr(feature = "clap", arg(long, required = true))]
    pub mqtt: Option<String>,
    /// The database: a libpq URL or key=value string, e.g. postgresql://user@host:5432/db.
    #[cfg_attr(feature = "clap", arg(long, required = true))]
    pub postgres: Option<String>,
    /// The rigs' topic template (as in `[output.mqtt] topic`).
    #[cfg_attr(feature = "clap", arg(long, default_value = "tagdeflect/{rig}/{test}"))]
    pub topic: String,
    /// Share the load with other archives: subscribe through the MQTT shared subscription
    /// `$share/<GROUP>/...`, so the broker hands each message to one archive of the group.
    /// Without it, a plain persistent subscription (what one archive needs; Mosquitto 2.0
    /// does not restore shared subscriptions after its own restart, plain ones it does).
    #[cfg_attr(feature = "clap", arg(long))]
    pub group: Option<String>,
    /// The MQTT client id; keep it fixed across restarts (the broker keeps the session),
    /// and different for each archive (default: tagdeflect-archive-<host>).
    #[cfg_attr(feature = "clap", arg(long))]
    pub client_id: Option<String>,
    /// TLS: PEM file of the CA certificates of the broker (mqtts://).
    #[cfg_attr(feature = "clap", arg(long))]
    pub ca_file: Option<std::path::PathBuf>,
    /// Feed lines per transaction at most.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 1000))]
    pub batch: usize,
}

/// What `tagdeflect archive` does instead of running.
#[derive(Debug, Clone)]
#[cfg_attr(feature = "clap", derive(clap::Subcommand))]
pub enum ArchiveCommand {
    /// Load a rig's feed file (or a test folder holding `feed.jsonl`) into the archive,
    /// idempotently: lines already held are left as they are (rigs that were away from the
    /// broker for longer than their buffer).
    Backfill(backfill::BackfillOptions),
}

/// Checks the options before anything connects (bad input: exit 2).
pub(crate) fn check_options(opts: &ArchiveOptions) -> Result<(TopicLayout, String, String), ArchiveError> {
    let mqtt = opts.mqtt.clone().ok_or_else(|| ArchiveError::BadOption("--mqtt URL is needed".into()))?;
    let postgres = opts.postgres.clone().ok_or_else(|| ArchiveError::BadOption("--postgres URL is needed".into()))?;
    tagdeflect_wire::BrokerUrl::parse(&mqtt).map_err(|m| ArchiveError::BadOption(format!("--mqtt: {m}")))?;
    let _: tokio_postgres::Config = postgres.parse().map_err(|e| ArchiveError::BadOption(format!("--postgres \"{postgres}\": {e}")))?;
    let layout = TopicLayout::new(&opts.topic).map_err(|m| ArchiveError::BadOption(format!("--topic: {m}")))?;
    if let Some(g) = &opts.group {
        tagdeflect_wire::check_level_name("--group", g).map_err(|m| ArchiveError::BadOption(m.to_string()))?;
    }
    if opts.batch == 0 {
        return Err(ArchiveError::BadOption("--batch must be at least 1".into()));
    }
    Ok((layout, mqtt, postgres))
}
