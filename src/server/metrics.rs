//! Prometheus metrics: requests and latency per transport, route and status; time per pipeline stage;
//! maps, keyframes and observations held; the CPU pool's queue; request body bytes read. Counts of maps are
//! read at scrape time.

use std::pin::Pin;
use std::sync::atomic::{AtomicU64, Ordering};
use std::task::{Context, Poll};

use axum::body::Bytes;

use parking_lot::Mutex;
use prometheus_client::encoding::text::encode;
use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{exponential_buckets, Histogram};
use prometheus_client::registry::Registry;

use crate::cpu_pool::PoolStats;
use crate::describe::pipeline::StageTimes;
use crate::service::Holdings;

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct RequestLabels {
    transport: String,
    route: String,
    status: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct RouteLabels {
    transport: String,
    route: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct TransportLabels {
    transport: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct StageLabels {
    stage: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct EventLabels {
    event: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct OperationLabels {
    operation: String,
}

type Seconds = Counter<f64, AtomicU64>;

/// Brings a counter up to a count kept elsewhere (the store's atomics, read at scrape time).
fn catch_up(counter: &Counter, total: u64) {
    let behind = total.saturating_sub(counter.get());
    if behind > 0 {
        counter.inc_by(behind);
    }
}

fn catch_up_seconds(counter: &Seconds, total: f64) {
    let behind = total - counter.get();
    if behind > 0.0 {
        counter.inc_by(behind);
    }
}

fn latency_histogram() -> Histogram {
    // 1 ms .. ~33 s
    Histogram::new(exponential_buckets(0.001, 2.0, 16))
}

/// The service's metrics.
pub struct Metrics {
    registry: Mutex<Registry>,
    requests: Family<RequestLabels, Counter>,
    latency: Family<RouteLabels, Histogram, fn() -> Histogram>,
    stages: Family<StageLabels, Histogram, fn() -> Histogram>,
    body_bytes: Family<TransportLabels, Counter>,
    maps: Gauge,
    held_back: Gauge,
    keyframes: Gauge,
    landmarks: Gauge,
    observations: Gauge,
    queued: Gauge,
    running: Gauge,
    rejected: Gauge,
    loaded_bytes: Gauge,
    cache_events: Family<EventLabels, Counter>,
    cache_load_seconds: Seconds,
    storage_requests: Family<OperationLabels, Counter>,
    storage_errors: Family<OperationLabels, Counter>,
    storage_seconds: Family<OperationLabels, Seconds>,
}

impl Default for Metrics {
    fn default() -> Self {
        Self::new()
    }
}

impl Metrics {
    pub fn new() -> Self {
        let mut registry = Registry::with_prefix("scone");
        let requests = Family::<RequestLabels, Counter>::default();
        registry.register("requests", "Requests by transport, route and status", requests.clone());
        let latency = Family::<RouteLabels, Histogram, fn() -> Histogram>::new_with_constructor(latency_histogram);
        registry.register("request_duration_seconds", "Request latency by transport and route", latency.clone());
        let stages = Family::<StageLabels, Histogram, fn() -> Histogram>::new_with_constructor(latency_histogram);
        registry.register("stage_duration_seconds", "Time per pipeline stage", stages.clone());
        let body_bytes = Family::<TransportLabels, Counter>::default();
        registry.register(
            "request_body_bytes",
            "Request body bytes read, by transport (refused requests' bodies are not read)",
            body_bytes.clone(),
        );
        let gauge = |registry: &mut Registry, name: &str, help: &str| {
            let g = Gauge::default();
            registry.register(name, help, g.clone());
            g
        };
        let maps = gauge(&mut registry, "maps", "Maps loaded");
        let held_back = gauge(&mut registry, "maps_held_back", "Maps that failed to load");
        let keyframes = gauge(&mut registry, "keyframes", "Keyframes in all maps");
        let landmarks = gauge(&mut registry, "landmarks", "Landmarks in all maps");
        let observations = gauge(&mut registry, "observations", "Live observations in all maps");
        let queued = gauge(&mut registry, "pool_queued", "Requests waiting for a CPU worker");
        let running = gauge(&mut registry, "pool_running", "Requests running on CPU workers");
        let rejected =
            gauge(&mut registry, "pool_rejected", "Requests refused because the queue was full (since start)");
        let loaded_bytes = gauge(&mut registry, "map_cache_bytes", "Estimated memory of the loaded maps");
        let cache_events = Family::<EventLabels, Counter>::default();
        registry.register(
            "map_cache_events",
            "Map cache: hit, miss, load, eviction, check (freshness), change (found changed), check_error, log_cut \
             (a load cut bytes off the end of a map's log: see GetMap's load_note)",
            cache_events.clone(),
        );
        let cache_load_seconds = Seconds::default();
        registry.register("map_cache_load_seconds", "Time spent loading maps", cache_load_seconds.clone());
        let storage_requests = Family::<OperationLabels, Counter>::default();
        registry.register("object_storage_requests", "Object storage calls by operation", storage_requests.clone());
        let storage_errors = Family::<OperationLabels, Counter>::default();
        registry.register(
            "object_storage_errors",
            "Object storage calls that failed (not found, not modified and failed conditions are answers, not failures)",
            storage_errors.clone(),
        );
        let storage_seconds = Family::<OperationLabels, Seconds>::default();
        registry.register("object_storage_seconds", "Time in object storage calls", storage_seconds.clone());
        Self {
            registry: Mutex::new(registry),
            requests,
            latency,
            stages,
            body_bytes,
            maps,
            held_back,
            keyframes,
            landmarks,
            observations,
            queued,
            running,
            rejected,
            loaded_bytes,
            cache_events,
            cache_load_seconds,
            storage_requests,
            storage_errors,
            storage_seconds,
        }
    }

    /// One finished request.
    pub fn request(&self, transport: &str, route: &str, status: &str, seconds: f64) {
        self.requests
            .get_or_create(&RequestLabels {
                transport: transport.to_string(),
                route: route.to_string(),
                status: status.to_string(),
            })
            .inc();
        self.latency
            .get_or_create(&RouteLabels { transport: transport.to_string(), route: route.to_string() })
            .observe(seconds);
    }

    /// The counter of body bytes read on `transport`, for [`CountedBody`].
    pub fn body_bytes(&self, transport: &str) -> Counter {
        self.body_bytes.get_or_create(&TransportLabels { transport: transport.to_string() }).clone()
    }

    /// Stage timings of one request.
    pub fn stages(&self, times: &StageTimes) {
        for (stage, s) in &times.0 {
            self.stages.get_or_create(&StageLabels { stage: stage.to_string() }).observe(*s);
        }
    }

    /// The text exposition, with the gauges read now.
    pub fn render(&self, holdings: Holdings, pool: &PoolStats) -> String {
        self.maps.set(holdings.maps as i64);
        self.held_back.set(holdings.held_back as i64);
        self.keyframes.set(holdings.keyframes as i64);
        self.landmarks.set(holdings.landmarks as i64);
        self.observations.set(holdings.observations as i64);
        self.queued.set(pool.queued.load(Ordering::Relaxed) as i64);
        self.running.set(pool.running.load(Ordering::Relaxed) as i64);
        self.rejected.set(pool.rejected.load(Ordering::Relaxed) as i64);
        self.loaded_bytes.set(holdings.loaded_bytes as i64);
        for (event, n) in &holdings.cache_events {
            catch_up(&self.cache_events.get_or_create(&EventLabels { event: event.to_string() }), *n);
        }
        catch_up_seconds(&self.cache_load_seconds, holdings.cache_load_seconds);
        for op in &holdings.storage {
            let labels = OperationLabels { operation: op.operation.to_string() };
            catch_up(&self.storage_requests.get_or_create(&labels), op.calls);
            catch_up(&self.storage_errors.get_or_create(&labels), op.errors);
            catch_up_seconds(&self.storage_seconds.get_or_create(&labels), op.seconds);
        }
        let mut out = String::new();
        if encode(&mut out, &self.registry.lock()).is_err() {
            out.clear();
        }
        out
    }
}

/// A request body that adds the bytes read from it to a counter.
pub struct CountedBody<B> {
    inner: B,
    bytes: Counter,
}

impl<B> CountedBody<B> {
    pub fn new(inner: B, bytes: Counter) -> Self {
        Self { inner, bytes }
    }
}

impl<B: http_body::Body<Data = Bytes> + Unpin> http_body::Body for CountedBody<B> {
    type Data = Bytes;
    type Error = B::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<http_body::Frame<Self::Data>, Self::Error>>> {
        let polled = Pin::new(&mut self.inner).poll_frame(cx);
        if let Poll::Ready(Some(Ok(frame))) = &polled {
            if let Some(data) = frame.data_ref() {
                self.bytes.inc_by(data.len() as u64);
            }
        }
        polled
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> http_body::SizeHint {
        self.inner.size_hint()
    }
}
