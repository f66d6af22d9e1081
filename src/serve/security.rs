//! Transport security and caller authentication: TLS from PEM files (optionally requiring client
//! certificates) and a shared bearer token checked on every call except health checks.

use std::path::PathBuf;

use tonic::transport::{Certificate, Identity, ServerTlsConfig};
use tonic::{Request, Status};

use crate::wire::{FileError, read_pem};

#[derive(Debug, thiserror::Error)]
pub enum SecurityError {
    #[error(transparent)]
    File(#[from] FileError),
    #[error("--tls-cert and --tls-key go together: {0} is missing")]
    HalfIdentity(&'static str),
    #[error("--tls-client-ca needs TLS: give --tls-cert and --tls-key too")]
    ClientCaWithoutTls,
}

/// Where the server's certificate chain and key are, and whose client certificates it accepts.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct TlsFiles {
    pub cert: Option<PathBuf>,
    pub key: Option<PathBuf>,
    /// CA bundle that client certificates must chain to; given, every client needs one.
    pub client_ca: Option<PathBuf>,
}

impl TlsFiles {
    /// The TLS setup these files describe; `None` when no certificate is given (plain HTTP/2).
    pub fn server_config(&self) -> Result<Option<ServerTlsConfig>, SecurityError> {
        let (cert, key) = match (&self.cert, &self.key) {
            (None, None) if self.client_ca.is_some() => return Err(SecurityError::ClientCaWithoutTls),
            (None, None) => return Ok(None),
            (Some(_), None) => return Err(SecurityError::HalfIdentity("--tls-key")),
            (None, Some(_)) => return Err(SecurityError::HalfIdentity("--tls-cert")),
            (Some(cert), Some(key)) => (cert, key),
        };
        let identity = Identity::from_pem(read_pem("certificate", cert)?, read_pem("private key", key)?);
        let mut config = ServerTlsConfig::new().identity(identity);
        if let Some(ca) = &self.client_ca {
            config = config.client_ca_root(Certificate::from_pem(read_pem("client CA", ca)?));
        }
        Ok(Some(config))
    }
}

/// Checks `authorization: Bearer <token>` on each call; passes every call when no token is set.
///
/// The presented token is hashed and the hashes compared (blake3's `Hash` compares in constant
/// time), so the time to refuse says nothing about how much of a guess was right.
#[derive(Debug, Clone, Default)]
pub struct RequireToken(Option<blake3::Hash>);

impl RequireToken {
    pub fn new(token: Option<&str>) -> Self {
        Self(token.map(|t| blake3::hash(t.as_bytes())))
    }
}

impl tonic::service::Interceptor for RequireToken {
    fn call(&mut self, request: Request<()>) -> Result<Request<()>, Status> {
        let Some(expected) = &self.0 else {
            return Ok(request);
        };
        let presented = request
            .metadata()
            .get("authorization")
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.strip_prefix("Bearer "));
        match presented {
            Some(token) if blake3::hash(token.as_bytes()) == *expected => Ok(request),
            // One answer for a missing, malformed and wrong token: nothing to learn from it.
            _ => Err(Status::unauthenticated("this server requires a valid bearer token")),
        }
    }
}

#[cfg(test)]
mod tests {
    use tonic::service::Interceptor;

    use super::*;

    fn call(check: &mut RequireToken, header: Option<&str>) -> Result<(), tonic::Code> {
        let mut request = Request::new(());
        if let Some(h) = header {
            request.metadata_mut().insert("authorization", h.parse().unwrap());
        }
        check.call(request).map(drop).map_err(|s| s.code())
    }

    #[test]
    fn only_the_exact_bearer_token_passes() {
        let mut check = RequireToken::new(Some("s3cret"));
        assert_eq!(call(&mut check, Some("Bearer s3cret")), Ok(()));
        for refused in [
            None,
            Some("Bearer s3cre"),
            Some("Bearer s3cret "),
            Some("s3cret"),
            Some("Basic s3cret"),
        ] {
            assert_eq!(
                call(&mut check, refused),
                Err(tonic::Code::Unauthenticated),
                "{refused:?}"
            );
        }
        assert_eq!(call(&mut RequireToken::new(None), None), Ok(()));
    }

    #[test]
    fn half_a_tls_setup_is_refused() {
        let files = |cert: bool, key: bool, ca: bool| TlsFiles {
            cert: cert.then(|| "c.pem".into()),
            key: key.then(|| "k.pem".into()),
            client_ca: ca.then(|| "ca.pem".into()),
        };
        assert!(matches!(files(false, false, false).server_config(), Ok(None)));
        assert!(matches!(
            files(true, false, false).server_config(),
            Err(SecurityError::HalfIdentity("--tls-key"))
        ));
        assert!(matches!(
            files(false, true, false).server_config(),
            Err(SecurityError::HalfIdentity("--tls-cert"))
        ));
        assert!(matches!(
            files(false, false, true).server_config(),
            Err(SecurityError::ClientCaWithoutTls)
        ));
    }
}
