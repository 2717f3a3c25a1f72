//! What the wire contract refuses.

/// A broker URL, topic, TLS setting or lab-test message that cannot be used; the message says
/// what and why (the caller adds where: the config key or the command-line option).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum WireError {
    /// A broker URL that does not parse.
    #[error("{0}")]
    Url(String),
    /// A topic template or a topic level (rig, test, group) that cannot be used.
    #[error("{0}")]
    Topic(String),
    /// The TLS configuration (CA bundle, client certificate or key) cannot be built.
    #[error("{0}")]
    Tls(String),
    /// A lab-test message the archive does not take.
    #[error("{0}")]
    LabTest(String),
}

impl From<WireError> for String {
    fn from(e: WireError) -> String {
        e.to_string()
    }
}
