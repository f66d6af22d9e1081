//! nak's own gRPC client connection (used by `nak bench`, `nak replay` and the Rust example): tuned
//! for full-field answers, with TLS and a bearer token when the server asks for them, and spread
//! over every server a target names.
//!
//! Balancing is per request, on the client: behind a Kubernetes ClusterIP Service every HTTP/2
//! connection (and so every request on it) would stay on one pod. A headless Service's name instead
//! resolves to every ready pod; the client resolves it again every [`ClientConfig::re_resolve`] and
//! adds or drops servers as pods come and go, choosing per request the less loaded of two
//! (tower's power of two choices).

mod credentials;
mod targets;

use std::collections::{HashMap, HashSet};
use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use tonic::service::interceptor::InterceptedService;
use tonic::transport::channel::Change;
use tonic::transport::{Certificate, Channel, ClientTlsConfig, Endpoint, Identity};

pub use credentials::Credentials;
pub use targets::{Target, TargetError};

use crate::proto::v1::deformation_client::DeformationClient;
use crate::wire::{FileError, read_pem, read_token};

/// A Deformation client that sends the configured credentials with every call.
pub type Client = DeformationClient<InterceptedService<Channel, Credentials>>;

/// The largest HTTP/2 frame (2²⁴ − 1 bytes, RFC 9113 §4.2).
const MAX_FRAME_SIZE: u32 = (1 << 24) - 1;

/// How to reach and authenticate to the servers.
#[derive(Debug, Clone, PartialEq)]
pub struct ClientConfig {
    /// One or more `http://host:port` or `https://host:port`, comma-separated.
    pub targets: String,
    /// CA bundle (PEM) to verify the servers' certificates; implies TLS.
    pub tls_ca: Option<PathBuf>,
    /// This client's certificate and key (PEM), for servers that require one.
    pub tls_cert: Option<PathBuf>,
    pub tls_key: Option<PathBuf>,
    /// Name to verify the server certificate against, when it is not the target's host.
    pub tls_domain: Option<String>,
    /// File holding the bearer token to send.
    pub auth_token_file: Option<PathBuf>,
    /// How often names are resolved again when balancing.
    pub re_resolve: Duration,
}

impl ClientConfig {
    pub fn new(targets: impl Into<String>) -> Self {
        Self {
            targets: targets.into(),
            tls_ca: None,
            tls_cert: None,
            tls_key: None,
            tls_domain: None,
            auth_token_file: None,
            re_resolve: Duration::from_secs(10),
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    #[error(transparent)]
    Target(#[from] TargetError),
    #[error(transparent)]
    File(#[from] FileError),
    #[error("the bearer token must be printable ASCII (it travels in an HTTP header)")]
    TokenNotAscii,
    #[error("--tls-cert and --tls-key go together")]
    HalfIdentity,
    #[error("cannot resolve {target}: {source}")]
    Resolve {
        target: String,
        #[source]
        source: std::io::Error,
    },
    #[error("{target} resolves to no address")]
    NoAddress { target: String },
    #[error("cannot connect to {target}: {source}")]
    Connect {
        target: String,
        #[source]
        source: tonic::transport::Error,
    },
}

/// Connects to the configured servers: directly when they are one address given by number, through
/// a per-request balancer over every resolved address otherwise.
pub async fn connect(config: &ClientConfig) -> Result<Client, ClientError> {
    let targets = Target::parse_list(&config.targets)?;
    let tls = tls_config(config, &targets)?;
    let credentials = Credentials::new(
        config
            .auth_token_file
            .as_deref()
            .map(read_token)
            .transpose()?
            .as_deref(),
    )?;
    let settings = Settings {
        tls,
        tls_domain: config.tls_domain.clone(),
    };
    let channel = match targets.as_slice() {
        [only] if only.is_address() => {
            let address = resolve(only).await?[0];
            settings
                .endpoint(only, address)?
                .connect()
                .await
                .map_err(|source| ClientError::Connect {
                    target: only.to_string(),
                    source,
                })?
        }
        _ => balanced(targets, settings, config.re_resolve).await?,
    };
    Ok(DeformationClient::with_interceptor(channel, credentials).max_decoding_message_size(256 << 20))
}

/// The TLS setup, when any target says https or a CA is given.
fn tls_config(config: &ClientConfig, targets: &[Target]) -> Result<Option<ClientTlsConfig>, ClientError> {
    let wanted = config.tls_ca.is_some() || targets.iter().any(|t| t.https);
    if !wanted {
        return Ok(None);
    }
    // A given CA is the only trust anchor (a private CA, as in a cluster); otherwise the system's roots.
    let mut tls = match &config.tls_ca {
        Some(ca) => ClientTlsConfig::new().ca_certificate(Certificate::from_pem(read_pem("CA bundle", ca)?)),
        None => ClientTlsConfig::new().with_native_roots(),
    };
    match (&config.tls_cert, &config.tls_key) {
        (Some(cert), Some(key)) => {
            tls = tls.identity(Identity::from_pem(
                read_pem("client certificate", cert)?,
                read_pem("client key", key)?,
            ));
        }
        (None, None) => {}
        _ => return Err(ClientError::HalfIdentity),
    }
    Ok(Some(tls))
}

/// Connection settings shared by every server of one client.
#[derive(Clone)]
struct Settings {
    tls: Option<ClientTlsConfig>,
    /// `--tls-domain`: the name certificates are verified against instead of each target's host.
    tls_domain: Option<String>,
}

impl Settings {
    /// An endpoint for `target` at one of its addresses: the connection goes to the address, and TLS
    /// verifies the certificate against the target's host name.
    fn endpoint(&self, target: &Target, address: SocketAddr) -> Result<Endpoint, ClientError> {
        let endpoint = Endpoint::from(target.uri_for(address))
            .tcp_nodelay(true)
            // A full field is ~116 kB: a window that holds it avoids a flow-control round trip per answer.
            .initial_stream_window_size(4 << 20)
            .initial_connection_window_size(8 << 20)
            // gRPC's default 16 KiB frames cut a full field into eight DATA frames, each framed and
            // written on its own; the largest frame HTTP/2 allows carries it in one.
            .max_frame_size(MAX_FRAME_SIZE);
        let Some(tls) = &self.tls else { return Ok(endpoint) };
        let domain = self.tls_domain.clone().unwrap_or_else(|| target.host.clone());
        endpoint
            .tls_config(tls.clone().domain_name(domain))
            .map_err(|source| ClientError::Connect {
                target: target.to_string(),
                source,
            })
    }
}

async fn resolve(target: &Target) -> Result<Vec<SocketAddr>, ClientError> {
    let addresses: Vec<SocketAddr> = tokio::net::lookup_host((target.host.as_str(), target.port))
        .await
        .map_err(|source| ClientError::Resolve {
            target: target.to_string(),
            source,
        })?
        .collect();
    if addresses.is_empty() {
        return Err(ClientError::NoAddress {
            target: target.to_string(),
        });
    }
    Ok(addresses)
}

type Key = (usize, SocketAddr);

/// Every address of every target, balanced per request; names are resolved again in the background
/// for as long as the channel lives.
///
/// At start each address is tried once and the unreachable ones are left out (`localhost` resolves to
/// `::1` too, where a server bound to 127.0.0.1 is not listening); if none answers, connecting fails
/// with the first error, as a direct connection would.
async fn balanced(targets: Vec<Target>, settings: Settings, re_resolve: Duration) -> Result<Channel, ClientError> {
    let mut reachable = HashMap::new();
    let mut first_error = None;
    for (index, target) in targets.iter().enumerate() {
        for address in resolve(target).await? {
            let endpoint = settings.endpoint(target, address)?;
            match endpoint.connect().await {
                Ok(_) => {
                    reachable.insert((index, address), endpoint);
                }
                Err(source) => {
                    first_error.get_or_insert(ClientError::Connect {
                        target: format!("{target} ({address})"),
                        source,
                    });
                }
            }
        }
    }
    if reachable.is_empty() {
        return Err(first_error.unwrap_or_else(|| ClientError::NoAddress {
            target: targets.iter().map(Target::to_string).collect::<Vec<_>>().join(","),
        }));
    }
    let (channel, changes) = Channel::balance_channel::<Key>(64);
    let known = reachable.keys().copied().collect();
    for (key, endpoint) in reachable {
        let _ = changes.send(Change::Insert(key, endpoint)).await;
    }
    tokio::spawn(follow_resolution(targets, settings, re_resolve, known, changes));
    Ok(channel)
}

/// Resolves the targets every `every` and tells the balancer which servers came and went, until the
/// channel is dropped. A failed lookup keeps the servers known so far.
async fn follow_resolution(
    targets: Vec<Target>,
    settings: Settings,
    every: Duration,
    mut known: HashSet<Key>,
    changes: tokio::sync::mpsc::Sender<Change<Key, Endpoint>>,
) {
    loop {
        tokio::select! {
            _ = changes.closed() => return,
            _ = tokio::time::sleep(every) => {}
        }
        let mut current = HashSet::new();
        for (index, target) in targets.iter().enumerate() {
            match resolve(target).await {
                Ok(addresses) => current.extend(addresses.into_iter().map(|a| (index, a))),
                Err(e) => {
                    tracing::warn!(error = %e, "cannot resolve again; keeping the servers known");
                    current.extend(known.iter().filter(|(i, _)| *i == index));
                }
            }
        }
        for &key in current.difference(&known) {
            // The same settings made endpoints for this target at start, so this does not fail in practice.
            let endpoint = match settings.endpoint(&targets[key.0], key.1) {
                Ok(endpoint) => endpoint,
                Err(e) => {
                    tracing::warn!(error = %e, server = %key.1, "cannot add server");
                    continue;
                }
            };
            tracing::info!(server = %key.1, "server added");
            let _ = changes.send(Change::Insert(key, endpoint)).await;
        }
        for &key in known.difference(&current) {
            tracing::info!(server = %key.1, "server removed");
            let _ = changes.send(Change::Remove(key)).await;
        }
        known = current;
    }
}
