//! The broker client's helpers, shared by the publisher and the archive: broker URLs, TLS
//! and connection options.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use rumqttc::{MqttOptions, TlsConfiguration, Transport};

use crate::WireError;

/// This machine's host name (`localhost` when unknown).
pub fn hostname() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .or_else(|_| std::fs::read_to_string("/etc/hostname"))
        .map(|s| s.trim().to_string())
        .ok()
        .filter(|s| !s.is_empty())
        .unwrap_or_else(|| "localhost".into())
}

/// A broker address parsed from `mqtt://` / `mqtts://` URLs.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BrokerUrl {
    /// True for `mqtts://` (also `ssl://`).
    pub tls: bool,
    /// Host name or address.
    pub host: String,
    /// TCP port.
    pub port: u16,
    /// User name given in the URL.
    pub username: Option<String>,
    /// Password given in the URL.
    pub password: Option<String>,
}

impl BrokerUrl {
    /// Parses `mqtt://[user[:password]@]host[:port]` (also `tcp://`; `mqtts://` / `ssl://` for TLS).
    pub fn parse(url: &str) -> Result<BrokerUrl, WireError> {
        let (scheme, rest) =
            url.split_once("://").ok_or_else(|| WireError::Url(format!("\"{url}\" is not a URL like mqtt://host:1883")))?;
        let tls = match scheme {
            "mqtt" | "tcp" => false,
            "mqtts" | "ssl" => true,
            _ => return Err(WireError::Url(format!("unknown scheme \"{scheme}\": expected mqtt:// or mqtts://"))),
        };
        let rest = rest.trim_end_matches('/');
        if rest.contains('/') || rest.contains('?') {
            return Err(WireError::Url(format!("\"{url}\": expected mqtt://host[:port] with no path")));
        }
        let (auth, hostport) = match rest.rsplit_once('@') {
            Some((a, h)) => (Some(a), h),
            None => (None, rest),
        };
        let (username, password) = match auth {
            None => (None, None),
            Some(a) => match a.split_once(':') {
                Some((u, p)) => (Some(u.to_string()), Some(p.to_string())),
                None => (Some(a.to_string()), None),
            },
        };
        let (host, port) = if let Some(h) = hostport.strip_prefix('[') {
            // [v6]:port
            let (h, p) = h.split_once(']').ok_or_else(|| WireError::Url(format!("\"{url}\": unclosed [ in the host")))?;
            (h.to_string(), p.strip_prefix(':'))
        } else {
            match hostport.rsplit_once(':') {
                Some((h, p)) => (h.to_string(), Some(p)),
                None => (hostport.to_string(), None),
            }
        };
        if host.is_empty() {
            return Err(WireError::Url(format!("\"{url}\": no host")));
        }
        let port = match port {
            Some(p) => p.parse::<u16>().map_err(|_| WireError::Url(format!("\"{url}\": port \"{p}\" is not a number 1..65535")))?,
            None if tls => 8883,
            None => 1883,
        };
        Ok(BrokerUrl { tls, host, port, username, password })
    }
}

/// Builds the rustls client configuration of a `mqtts://` connection: the CA bundle
/// (default: the system's), and optionally a client certificate and key (PEM files).
pub fn tls_config_for(
    ca_file: Option<&Path>,
    client_cert: Option<&Path>,
    client_key: Option<&Path>,
) -> Result<Arc<rustls::ClientConfig>, WireError> {
    use rustls::pki_types::pem::PemObject;
    use rustls::pki_types::{CertificateDer, PrivateKeyDer};
    let ca = ca_file.map(Path::to_path_buf).unwrap_or_else(|| PathBuf::from("/etc/ssl/certs/ca-certificates.crt"));
    let mut roots = rustls::RootCertStore::empty();
    let certs = CertificateDer::pem_file_iter(&ca).map_err(|e| WireError::Tls(format!("{}: {e}", ca.display())))?;
    for c in certs {
        let c = c.map_err(|e| WireError::Tls(format!("{}: {e}", ca.display())))?;
        roots.add(c).map_err(|e| WireError::Tls(format!("{}: {e}", ca.display())))?;
    }
    if roots.is_empty() {
        return Err(WireError::Tls(format!("{}: no CA certificate in it", ca.display())));
    }
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let builder = rustls::ClientConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .map_err(|e| WireError::Tls(e.to_string()))?
        .with_root_certificates(roots);
    let config = match (client_cert, client_key) {
        (Some(cert), Some(key)) => {
            let chain: Vec<CertificateDer<'static>> = CertificateDer::pem_file_iter(cert)
                .and_then(|it| it.collect::<Result<Vec<_>, _>>())
                .map_err(|e| WireError::Tls(format!("{}: {e}", cert.display())))?;
            let key = PrivateKeyDer::from_pem_file(key).map_err(|e| WireError::Tls(format!("{}: {e}", key.display())))?;
            builder.with_client_auth_cert(chain, key).map_err(|e| WireError::Tls(format!("client certificate: {e}")))?
        }
        _ => builder.with_no_client_auth(),
    };
    Ok(Arc::new(config))
}

/// Connection options for a broker URL (TLS, credentials from the URL or given).
pub fn mqtt_options(
    url: &str,
    client_id: &str,
    username: Option<&str>,
    password: Option<&str>,
    tls: Option<Arc<rustls::ClientConfig>>,
) -> Result<MqttOptions, WireError> {
    let u = BrokerUrl::parse(url)?;
    let mut o = MqttOptions::new(client_id, u.host.clone(), u.port);
    if u.tls {
        let cfg = match tls {
            Some(c) => c,
            None => tls_config_for(None, None, None)?,
        };
        o.set_transport(Transport::tls_with_config(TlsConfiguration::Rustls(cfg)));
    }
    let user = username.map(str::to_string).or(u.username);
    let pass = password.map(str::to_string).or(u.password);
    if let Some(user) = user {
        o.set_credentials(user, pass.unwrap_or_default());
    }
    // Feed lines of a big rig are a few kB; leave ample room.
    o.set_max_packet_size(1 << 20, 1 << 20);
    Ok(o)
}
