//! Each call at its arrival: the instant its deadline counts from, and, for a unary `Predict`, its
//! place under the admission bound.
//!
//! A quick request is computed on the runtime thread that reads it. While those threads are busy,
//! calls that have arrived wait for them in HTTP/2 and tokio, so a bound taken when the handler
//! finally runs would never be reached: overload would queue instead of being refused. Taken here,
//! where the call's headers arrive, the place is held from arrival until the call is answered, and a
//! call beyond the bound is refused with RESOURCE_EXHAUSTED before anything else is done for it.

use std::future::Future;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Instant;

use tonic::codegen::http;
use tonic::server::NamedService;
use tower::util::MapRequestLayer;
use tower::{Layer, Service};

use super::admission::{Admission, Permit};
use super::metrics::Metrics;

/// The unary call admitted at arrival. A stream's messages are admitted one by one as they are read
/// (a stream holds a place only while one of its messages is being answered).
const PREDICT: &str = "/nak.v1.Deformation/Predict";

/// When a call's headers arrived: the point where tonic's own deadline timer starts. The handler
/// runs only once the message has arrived and been decoded, later by as much as a busy machine
/// delays it, so a deadline counted from there could overshoot the caller's.
#[derive(Clone, Copy, Debug)]
pub struct Arrival(Instant);

/// The place a call took at its arrival; it is freed when the last handle to the call is dropped,
/// after its answer.
#[derive(Clone, Debug)]
pub struct Admitted(pub Arc<Permit>);

/// Stamps each call with its [`Arrival`], outermost, where tonic's own deadline timer starts.
pub fn stamp_layer<B>() -> MapRequestLayer<fn(http::Request<B>) -> http::Request<B>> {
    MapRequestLayer::new(|mut request: http::Request<B>| {
        stamp(&mut request);
        request
    })
}

/// Stamps `request` with its arrival, unless a layer further out did.
fn stamp<B>(request: &mut http::Request<B>) {
    if request.extensions().get::<Arrival>().is_none() {
        request.extensions_mut().insert(Arrival(Instant::now()));
    }
}

/// When `request` arrived: its [`Arrival`] stamp, or now where no layer stamped it.
pub fn arrival<T>(request: &tonic::Request<T>) -> Instant {
    request
        .extensions()
        .get::<Arrival>()
        .map_or_else(Instant::now, |arrival| arrival.0)
}

/// The place `request` took at its arrival, if the layer admitted it (taken out of the request).
pub fn admitted<T>(request: &mut tonic::Request<T>) -> Option<Admitted> {
    request.extensions_mut().remove::<Admitted>()
}

/// Admits each unary `Predict` call as it arrives, or refuses it at once (and stamps its
/// [`Arrival`] if [`stamp_layer`] did not).
#[derive(Clone)]
pub struct ArrivalLayer {
    admission: Arc<Admission>,
    metrics: Option<Arc<Metrics>>,
}

impl ArrivalLayer {
    /// Refusals are counted by `admission` and, when given, in `metrics`' request counts.
    pub fn new(admission: Arc<Admission>, metrics: Option<Arc<Metrics>>) -> Self {
        Self { admission, metrics }
    }
}

impl<S> Layer<S> for ArrivalLayer {
    type Service = AtArrival<S>;

    fn layer(&self, inner: S) -> Self::Service {
        AtArrival {
            inner,
            layer: self.clone(),
        }
    }
}

/// The service [`ArrivalLayer`] wraps.
#[derive(Clone)]
pub struct AtArrival<S> {
    inner: S,
    layer: ArrivalLayer,
}

impl<S: NamedService> NamedService for AtArrival<S> {
    const NAME: &'static str = S::NAME;
}

impl<S, B, R> Service<http::Request<B>> for AtArrival<S>
where
    S: Service<http::Request<B>, Response = http::Response<R>>,
    S::Future: Send + 'static,
    S::Error: Send + 'static,
    R: Default + Send + 'static,
{
    type Response = http::Response<R>;
    type Error = S::Error;
    type Future = Pin<Box<dyn Future<Output = Result<Self::Response, S::Error>> + Send>>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, mut request: http::Request<B>) -> Self::Future {
        stamp(&mut request);
        if request.uri().path() == PREDICT {
            match self.layer.admission.try_admit() {
                Some(permit) => {
                    request.extensions_mut().insert(Admitted(Arc::new(permit)));
                }
                None => {
                    if let Some(metrics) = &self.layer.metrics {
                        metrics.observe_refused_at_arrival();
                    }
                    let refusal = self.layer.admission.at_capacity().into_http();
                    return Box::pin(std::future::ready(Ok(refusal)));
                }
            }
        }
        Box::pin(self.inner.call(request))
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use tokio::sync::oneshot;
    use tower::ServiceExt;

    use super::*;

    /// A call to `path` through the layer around a service that answers only when `release` fires.
    async fn call(
        layer: &ArrivalLayer,
        path: &str,
        release: oneshot::Receiver<()>,
    ) -> tokio::task::JoinHandle<http::Response<String>> {
        let release = std::sync::Mutex::new(Some(release));
        let held = tower::service_fn(move |request: http::Request<()>| {
            let release = release.lock().unwrap().take();
            async move {
                if let Some(release) = release {
                    let _ = release.await;
                }
                drop(request);
                Ok::<_, std::convert::Infallible>(http::Response::new("answered".to_owned()))
            }
        });
        let service = layer.layer(held);
        let request = http::Request::builder().uri(path).body(()).unwrap();
        tokio::spawn(async move { service.oneshot(request).await.unwrap() })
    }

    fn status(response: &http::Response<String>) -> Option<&str> {
        response.headers().get("grpc-status").and_then(|v| v.to_str().ok())
    }

    #[tokio::test]
    async fn a_call_beyond_the_bound_is_refused_at_arrival_and_places_free_when_calls_are_answered() {
        let admission = Admission::new(1);
        let layer = ArrivalLayer::new(admission.clone(), None);
        let (first, hold) = oneshot::channel();
        let held = call(&layer, PREDICT, hold).await;
        tokio::time::sleep(Duration::from_millis(20)).await;
        assert_eq!(
            admission.status().in_flight,
            1,
            "the first call holds its place while unanswered"
        );
        // The second is refused without its service being called: RESOURCE_EXHAUSTED (8).
        let (_never, wait) = oneshot::channel();
        let refused = call(&layer, PREDICT, wait).await.await.unwrap();
        assert_eq!(status(&refused), Some("8"));
        assert_eq!(admission.status().refused, 1);
        // Other methods (here GetStatus) are not admitted, and pass while the place is taken.
        let (now, go) = oneshot::channel();
        let _ = now.send(());
        let other = call(&layer, "/nak.v1.Deformation/GetStatus", go).await.await.unwrap();
        assert_eq!(other.body(), "answered");
        let _ = first.send(());
        assert_eq!(held.await.unwrap().body(), "answered");
        assert_eq!(admission.status().in_flight, 0, "an answered call frees its place");
        let (again, go) = oneshot::channel();
        let _ = again.send(());
        assert_eq!(call(&layer, PREDICT, go).await.await.unwrap().body(), "answered");
        assert_eq!(admission.status().refused, 1);
    }

    #[tokio::test]
    async fn a_call_arrives_when_the_layer_stamps_it_not_when_its_handler_runs() {
        let echo = tower::service_fn(|request: http::Request<()>| async move {
            Ok::<_, std::convert::Infallible>(http::Response::new(request))
        });
        let service = ArrivalLayer::new(Admission::new(1), None).layer(echo);
        let before = Instant::now();
        let request = http::Request::builder().uri("/other").body(()).unwrap();
        let echoed = service.oneshot(request).await.map(http::Response::into_body);
        let request = tonic::Request::from_http(echoed.unwrap());
        tokio::time::sleep(Duration::from_millis(20)).await;
        let arrived = arrival(&request);
        assert!(arrived >= before && arrived.elapsed() >= Duration::from_millis(20));
        // Unstamped (a service called without the layer): now.
        assert!(arrival(&tonic::Request::new(())).elapsed() < Duration::from_millis(20));
    }
}
