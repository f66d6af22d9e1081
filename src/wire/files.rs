//! The files a TLS connection and a bearer token come from, read with errors that name the file.

use std::path::{Path, PathBuf};

#[derive(Debug, thiserror::Error)]
pub enum FileError {
    #[error("cannot read {what} {}: {source}", path.display())]
    Read {
        what: &'static str,
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{} holds no PEM {what} (expected a '-----BEGIN' block)", path.display())]
    NotPem { what: &'static str, path: PathBuf },
    #[error("the bearer token file {} is empty", .0.display())]
    EmptyToken(PathBuf),
}

/// A PEM file's bytes, refused early (with its path) when it is not PEM: rustls's own error names
/// neither the file nor the problem.
pub fn read_pem(what: &'static str, path: &Path) -> Result<Vec<u8>, FileError> {
    let bytes = std::fs::read(path).map_err(|source| FileError::Read {
        what,
        path: path.to_owned(),
        source,
    })?;
    if !bytes.windows(10).any(|w| w == b"-----BEGIN") {
        return Err(FileError::NotPem {
            what,
            path: path.to_owned(),
        });
    }
    Ok(bytes)
}

/// The token in `path`, without surrounding whitespace (files usually end in a newline).
pub fn read_token(path: &Path) -> Result<String, FileError> {
    let text = std::fs::read_to_string(path).map_err(|source| FileError::Read {
        what: "bearer token file",
        path: path.to_owned(),
        source,
    })?;
    let token = text.trim();
    if token.is_empty() {
        return Err(FileError::EmptyToken(path.to_owned()));
    }
    Ok(token.to_owned())
}
