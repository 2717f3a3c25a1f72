//! The errors of `tagdeflect archive` and `tagdeflect archive-bench`.

/// Why `tagdeflect archive` or `tagdeflect archive-bench` stopped with an error.
///
/// **Bad input or runtime failure.** [`ArchiveError::is_bad_input`] tells the two apart:
///
/// - *Bad input* (the command line exits 2, and systemd does not restart the archive:
///   `RestartPreventExitStatus=2`): [`BadOption`](Self::BadOption) — an option that cannot
///   be used (`--mqtt`, `--postgres`, `--topic`, `--group`, `--batch`, `--ca-file` and the CA
///   bundle it names or the system's).
/// - *Runtime failure* (exit 1, a restart may cure it): the async runtime that cannot start
///   ([`Runtime`](Self::Runtime)) and, in `archive-bench`, a local server that cannot start
///   ([`LocalServer`](Self::LocalServer)), publishing that fails ([`Publish`](Self::Publish),
///   [`Task`](Self::Task)) and an archive that does not keep up ([`Bench`](Self::Bench)).
///
/// Outages of the broker or the database are no error: the archive retries them.
///
/// **Messages.** A variant that adds context holds its cause in its own message
/// (`context: cause`, what the command line's `{:#}` printed before: the local servers'
/// I/O errors carry their whole story in their message, they have no sources) and returns
/// no [`source`](std::error::Error::source), so printing it with `{:#}` through `anyhow`
/// does not repeat the cause; a variant that wraps another error alone is transparent (its
/// message and sources are that error's).
#[derive(Debug, thiserror::Error)]
pub enum ArchiveError {
    /// An option that cannot be used (bad input); the message names it.
    #[error("{0}")]
    BadOption(String),
    /// The async runtime could not be started (runtime failure).
    #[error(transparent)]
    Runtime(std::io::Error),
    /// `archive-bench`: a local Mosquitto or PostgreSQL could not be started (runtime failure).
    #[error("cannot start a local {server}: {cause}")]
    LocalServer {
        /// "Mosquitto" or "PostgreSQL".
        server: &'static str,
        /// Why.
        cause: std::io::Error,
    },
    /// `archive-bench`: a feed line could not be published (runtime failure).
    #[error(transparent)]
    Publish(#[from] rumqttc::ClientError),
    /// `archive-bench`: a publishing rig's task failed (runtime failure).
    #[error(transparent)]
    Task(#[from] tokio::task::JoinError),
    /// `archive-bench`: the archive did not store the lines in time (runtime failure).
    #[error("{0}")]
    Bench(String),
    /// `archive backfill`: the database or the broker failed (runtime failure); the message
    /// holds the whole chain of causes.
    #[error("{0}")]
    Database(String),
}

impl ArchiveError {
    /// True for bad input (the command line exits 2), false for a runtime failure (exit 1);
    /// see the type's documentation for which is which.
    pub fn is_bad_input(&self) -> bool {
        match self {
            ArchiveError::BadOption(_) => true,
            ArchiveError::Runtime(_)
            | ArchiveError::LocalServer { .. }
            | ArchiveError::Publish(_)
            | ArchiveError::Task(_)
            | ArchiveError::Bench(_)
            | ArchiveError::Database(_) => false,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn messages_hold_their_cause_and_name_the_kind() {
        let cause = std::io::Error::other("cannot start mosquitto (run scripts/setup.sh): No such file or directory");
        let e = ArchiveError::LocalServer { server: "Mosquitto", cause };
        assert_eq!(
            e.to_string(),
            "cannot start a local Mosquitto: cannot start mosquitto (run scripts/setup.sh): No such file or directory"
        );
        assert!(std::error::Error::source(&e).is_none(), "the cause is in the message, not repeated by `{{:#}}`");
        assert!(!e.is_bad_input());
        assert!(ArchiveError::BadOption("--batch must be at least 1".into()).is_bad_input());
        fn send_sync<T: Send + Sync + 'static>() {}
        send_sync::<ArchiveError>();
    }
}
