//! `nak serve --ui`: a page of its own for looking at the organ and pulling on it. The page reaches
//! the same `nak.v1.Deformation` service as every other client, through gRPC-Web on this port (a
//! browser cannot speak gRPC's HTTP/2 trailers), so it sees only the public API: the same admission,
//! token check, metrics and recording. Its code is written here and embedded in the binary; nothing
//! is fetched when it runs.

use std::convert::Infallible;

use axum::http::header::{CACHE_CONTROL, CONTENT_TYPE};
use axum::response::IntoResponse;
use axum::routing::get;
use bytes::Bytes;
use tokio::net::TcpListener;
use tonic::body::Body;
use tonic::codegen::http::{Request, Response};
use tonic::codegen::{Body as HttpBody, StdError};
use tonic::server::NamedService;
use tower::{Service, ServiceBuilder};

use super::status_codes;

const PAGE: &str = include_str!("ui/index.html");
const JAVASCRIPT: &str = "text/javascript; charset=utf-8";
/// The page's ES modules, by the path it imports them from.
const MODULES: [(&str, &str); 3] = [
    ("/viewer.js", include_str!("ui/viewer.js")),
    ("/scene.js", include_str!("ui/scene.js")),
    ("/grpc_web.js", include_str!("ui/grpc_web.js")),
];

/// Serves the page at `/` and `service` as gRPC-Web until `shutdown` completes.
pub async fn serve<S, B>(
    service: S,
    listener: TcpListener,
    shutdown: impl std::future::Future<Output = ()> + Send + 'static,
) -> std::io::Result<()>
where
    S: Service<Request<Body>, Response = Response<B>, Error = Infallible>
        + NamedService
        + Clone
        + Send
        + Sync
        + 'static,
    S::Future: Send + 'static,
    B: HttpBody<Data = Bytes> + Send + 'static,
    B::Error: Into<StdError> + std::fmt::Display,
{
    let grpc_web = ServiceBuilder::new()
        .layer(tonic_web::GrpcWebLayer::new())
        .layer(status_codes::layer())
        .layer(super::arrival::stamp_layer())
        .service(service);
    let mut app = axum::Router::new().route("/", get(|| asset("text/html; charset=utf-8", PAGE)));
    for (path, source) in MODULES {
        app = app.route(path, get(move || asset(JAVASCRIPT, source)));
    }
    let app = app.route_service(&format!("/{}/{{*method}}", S::NAME), grpc_web);
    axum::serve(listener, app).with_graceful_shutdown(shutdown).await
}

/// An embedded file. `no-cache` makes a browser revalidate, so a page left open across a server
/// upgrade does not run an old script against a new API.
async fn asset(content_type: &'static str, body: &'static str) -> impl IntoResponse {
    ([(CONTENT_TYPE, content_type), (CACHE_CONTROL, "no-cache")], body)
}
