//! The flags every subcommand that talks to a server shares: where it is and how to authenticate.

use std::path::PathBuf;

use nak::client::ClientConfig;

#[derive(clap::Args)]
pub struct ConnectArgs {
    /// Server to talk to: http://host:port or https://host:port. Several, comma-separated, or a name
    /// that resolves to several addresses (a Kubernetes headless Service): requests are spread over
    /// every one, and names are resolved again every 10 s.
    #[arg(long, default_value = "http://127.0.0.1:50051")]
    target: String,
    /// CA bundle (PEM) that the server's certificate must chain to; implies TLS. https targets
    /// without it are checked against the system's roots.
    #[arg(long, value_name = "PEM")]
    tls_ca: Option<PathBuf>,
    /// This client's certificate (PEM), for servers that require one; with --tls-key.
    #[arg(long, value_name = "PEM")]
    tls_cert: Option<PathBuf>,
    /// This client's private key (PEM); with --tls-cert.
    #[arg(long, value_name = "PEM")]
    tls_key: Option<PathBuf>,
    /// Name the server certificate must carry, when it is not the target's host.
    #[arg(long, value_name = "NAME")]
    tls_domain: Option<String>,
    /// A file holding the bearer token to send with every call.
    #[arg(long, value_name = "FILE")]
    auth_token_file: Option<PathBuf>,
}

impl ConnectArgs {
    pub fn config(self) -> ClientConfig {
        ClientConfig {
            tls_ca: self.tls_ca,
            tls_cert: self.tls_cert,
            tls_key: self.tls_key,
            tls_domain: self.tls_domain,
            auth_token_file: self.auth_token_file,
            ..ClientConfig::new(self.target)
        }
    }
}
