//! gRPC says RESOURCE_EXHAUSTED for a message over the size limit; tonic's decoder says OUT_OF_RANGE.
//! This layer rewrites that one status on unary responses (trailers-only, so the status is in the
//! headers); streaming calls map it where the stream is read.

use tonic::codegen::http::{HeaderValue, Response};
use tower::util::MapResponseLayer;

/// tonic's wording for an oversize message (codec/decode.rs).
pub const TOO_LARGE: &str = "message length too large";

const OUT_OF_RANGE: &str = "11";
const RESOURCE_EXHAUSTED: &str = "8";

pub fn layer<B>() -> MapResponseLayer<fn(Response<B>) -> Response<B>> {
    MapResponseLayer::new(rewrite::<B>)
}

fn rewrite<B>(mut response: Response<B>) -> Response<B> {
    let headers = response.headers();
    let out_of_range = headers.get("grpc-status").is_some_and(|s| s == OUT_OF_RANGE);
    let too_large = headers
        .get("grpc-message")
        .and_then(|m| m.to_str().ok())
        .is_some_and(|m| m.contains("message%20length%20too%20large") || m.contains(TOO_LARGE));
    if out_of_range && too_large {
        response
            .headers_mut()
            .insert("grpc-status", HeaderValue::from_static(RESOURCE_EXHAUSTED));
    }
    response
}
