//! Where a client connects: `http://host:port` or `https://host:port`, one or several.

use std::fmt;
use std::net::{IpAddr, SocketAddr};

use tonic::codegen::http::Uri;

/// The gRPC port nak serves on by default.
const DEFAULT_PORT: u16 = 50051;

#[derive(Debug, thiserror::Error)]
pub enum TargetError {
    #[error("no server given: expected http://host:port (several separated by commas)")]
    Empty,
    #[error("{text:?} is not a server address: expected http://host:port or https://host:port")]
    Invalid { text: String },
}

/// One server name (or address) and port.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Target {
    pub https: bool,
    pub host: String,
    pub port: u16,
}

impl Target {
    /// Parses `http[s]://host[:port]` (port 50051 when absent).
    pub fn parse(text: &str) -> Result<Self, TargetError> {
        let invalid = || TargetError::Invalid { text: text.to_owned() };
        let uri: Uri = text.trim().parse().map_err(|_| invalid())?;
        let https = match uri.scheme_str() {
            Some("http") => false,
            Some("https") => true,
            _ => return Err(invalid()),
        };
        if uri.path() != "/" && !uri.path().is_empty() {
            return Err(invalid());
        }
        let host = uri.host().ok_or_else(invalid)?;
        // IPv6 literals come bracketed in URIs; lookups and TLS names want them bare.
        let host = host.trim_start_matches('[').trim_end_matches(']').to_owned();
        // `Uri` drops a port it cannot read (`host:99999`) rather than refusing it.
        let authority = uri.authority().map_or("", |a| a.as_str());
        let after_host = authority.rsplit_once(']').map_or(authority, |(_, rest)| rest);
        let port = match uri.port_u16() {
            Some(port) => port,
            None if after_host.contains(':') => return Err(invalid()),
            None => DEFAULT_PORT,
        };
        Ok(Self { https, host, port })
    }

    /// Parses a comma-separated list of targets.
    pub fn parse_list(text: &str) -> Result<Vec<Self>, TargetError> {
        let targets = text
            .split(',')
            .filter(|t| !t.trim().is_empty())
            .map(Self::parse)
            .collect::<Result<Vec<_>, _>>()?;
        if targets.is_empty() {
            return Err(TargetError::Empty);
        }
        Ok(targets)
    }

    /// Whether the host is an IP address rather than a name (nothing to resolve, nothing to follow).
    pub fn is_address(&self) -> bool {
        self.host.parse::<IpAddr>().is_ok()
    }

    /// The URI to connect to this target at `address`, with this target's scheme.
    pub fn uri_for(&self, address: SocketAddr) -> Uri {
        let scheme = if self.https { "https" } else { "http" };
        // A SocketAddr's Display form (`[::1]:50051`, `127.0.0.1:50051`) is a valid authority.
        Uri::builder()
            .scheme(scheme)
            .authority(address.to_string())
            .path_and_query("/")
            .build()
            .unwrap_or_default()
    }
}

impl fmt::Display for Target {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let scheme = if self.https { "https" } else { "http" };
        match self.host.contains(':') {
            true => write!(f, "{scheme}://[{}]:{}", self.host, self.port),
            false => write!(f, "{scheme}://{}:{}", self.host, self.port),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn targets_parse_with_their_scheme_host_and_port() {
        let t = Target::parse("https://nak.sim.svc:7000").unwrap();
        assert_eq!((t.https, t.host.as_str(), t.port), (true, "nak.sim.svc", 7000));
        assert!(!t.is_address());
        let t = Target::parse("http://[::1]:50051").unwrap();
        assert_eq!((t.host.as_str(), t.is_address()), ("::1", true));
        assert_eq!(t.to_string(), "http://[::1]:50051");
        assert_eq!(Target::parse("http://10.0.0.7").unwrap().port, 50051);
        let list = Target::parse_list("http://127.0.0.1:1, http://127.0.0.1:2,").unwrap();
        assert_eq!(list.iter().map(|t| t.port).collect::<Vec<_>>(), [1, 2]);
        let uri = list[0].uri_for("[::1]:9".parse().unwrap());
        assert_eq!(uri.to_string(), "http://[::1]:9/");
    }

    #[test]
    fn what_is_not_a_server_address_is_refused() {
        for bad in [
            "127.0.0.1:50051",
            "ftp://host:1",
            "http://host:1/path",
            "http://",
            "http://host:99999",
        ] {
            assert!(matches!(Target::parse(bad), Err(TargetError::Invalid { .. })), "{bad}");
        }
        assert!(matches!(Target::parse_list(" , "), Err(TargetError::Empty)));
    }
}
