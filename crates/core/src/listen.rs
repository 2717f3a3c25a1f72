//! The one rule for an address a server listens on (`[output] http`, `--http`,
//! `[output.control] modbus`, `demo --control`).
//!
//! Accepted: `IP:PORT` (`127.0.0.1:8080`, `0.0.0.0:5020`), `[IPv6]:PORT` (`[::1]:0`) and
//! `localhost:PORT` (read as `127.0.0.1:PORT`). Port 0 asks for any free port. Nothing else:
//! no other host name (a name would be resolved at start, and could resolve to an address
//! other than the one meant), no address without its port, no port above 65 535.

use std::net::SocketAddr;

/// An address that is not a listen address, and an example of one for the message.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("\"{text}\" is not a listen address: expected IP:PORT, e.g. \"127.0.0.1:{example_port}\" (loopback) or \"0.0.0.0:{example_port}\"")]
pub struct ListenAddrError {
    /// What was given.
    pub text: String,
    /// The port of the examples the message gives (the server's usual one).
    pub example_port: u16,
}

/// Parses a listen address by the rule of the module docs; `example_port` is the port the
/// error message's examples use.
pub fn parse_listen_addr(s: &str, example_port: u16) -> Result<SocketAddr, ListenAddrError> {
    if let Ok(a) = s.parse::<SocketAddr>() {
        return Ok(a);
    }
    let bad = || ListenAddrError { text: s.to_string(), example_port };
    match s.rsplit_once(':') {
        Some(("localhost", port)) => port.parse::<u16>().map(|p| SocketAddr::from(([127, 0, 0, 1], p))).map_err(|_| bad()),
        _ => Err(bad()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ip_ipv6_and_localhost_with_a_port() {
        assert_eq!(parse_listen_addr("127.0.0.1:8080", 8080).unwrap(), SocketAddr::from(([127, 0, 0, 1], 8080)));
        assert_eq!(parse_listen_addr("0.0.0.0:5020", 5020).unwrap(), SocketAddr::from(([0, 0, 0, 0], 5020)));
        assert_eq!(parse_listen_addr("localhost:9000", 8080).unwrap(), SocketAddr::from(([127, 0, 0, 1], 9000)));
        assert!(parse_listen_addr("[::1]:0", 8080).unwrap().ip().is_loopback());
    }

    #[test]
    fn anything_else_is_refused_with_an_example() {
        for bad in ["8080", "127.0.0.1", "127.0.0.1:99999", "lab-pc:80", "localhost", "localhost:x", ""] {
            let e = parse_listen_addr(bad, 5020).unwrap_err();
            assert_eq!(
                e.to_string(),
                format!("\"{bad}\" is not a listen address: expected IP:PORT, e.g. \"127.0.0.1:5020\" (loopback) or \"0.0.0.0:5020\"")
            );
        }
    }
}
