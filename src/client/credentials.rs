//! The bearer token a client sends with every call.

use tonic::metadata::{Ascii, MetadataValue};
use tonic::{Request, Status};

use super::ClientError;

/// Adds `authorization: Bearer <token>` to each call, when a token is set.
#[derive(Debug, Clone, Default)]
pub struct Credentials(Option<MetadataValue<Ascii>>);

impl Credentials {
    pub fn new(token: Option<&str>) -> Result<Self, ClientError> {
        let header = token
            .map(|t| format!("Bearer {t}").parse().map_err(|_| ClientError::TokenNotAscii))
            .transpose()?;
        Ok(Self(header))
    }
}

impl tonic::service::Interceptor for Credentials {
    fn call(&mut self, mut request: Request<()>) -> Result<Request<()>, Status> {
        if let Some(header) = &self.0 {
            request.metadata_mut().insert("authorization", header.clone());
        }
        Ok(request)
    }
}
