//! Prometheus metrics. Counted as they happen: requests and latency per transport, route and status; time per
//! pipeline stage; request body bytes read. Read at each scrape from where they are kept ([`Source`], encoded
//! by a prometheus-client [`Collector`]): maps, keyframes and observations held, the map cache's and object
//! storage's counts, the CPU pool's queue and its refusals.

use std::fmt;
use std::pin::Pin;
use std::sync::atomic::Ordering;
use std::sync::Weak;
use std::task::{Context, Poll};

use axum::body::Bytes;

use parking_lot::Mutex;
use prometheus_client::collector::Collector;
use prometheus_client::encoding::text::encode;
use prometheus_client::encoding::{DescriptorEncoder, EncodeCounterValue, EncodeLabelSet, EncodeMetric};
use prometheus_client::metrics::counter::{ConstCounter, Counter};
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::ConstGauge;
use prometheus_client::metrics::histogram::{exponential_buckets, Histogram};
use prometheus_client::metrics::MetricType;
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

fn latency_histogram() -> Histogram {
    // 1 ms .. ~33 s
    Histogram::new(exponential_buckets(0.001, 2.0, 16))
}

/// Where the values read at scrape time are kept (the server's `App`).
pub trait Source: Send + Sync + 'static {
    /// What the service holds, with the map cache's and object storage's counts since start.
    fn holdings(&self) -> Holdings;
    /// The CPU pool's queue, and its refusals since start.
    fn pool(&self) -> &PoolStats;
}

/// Encodes, at each scrape, what its [`Source`] holds then (nothing once the source is gone: the source owns
/// the metrics, so it is held weakly).
struct ReadAtScrape(Weak<dyn Source>);

impl fmt::Debug for ReadAtScrape {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("ReadAtScrape")
    }
}

fn gauge(encoder: &mut DescriptorEncoder, name: &str, help: &str, value: impl TryInto<i64>) -> fmt::Result {
    let value = value.try_into().unwrap_or(i64::MAX);
    ConstGauge::new(value).encode(encoder.encode_descriptor(name, help, None, MetricType::Gauge)?)
}

fn counter(encoder: &mut DescriptorEncoder, name: &str, help: &str, value: impl EncodeCounterValue) -> fmt::Result {
    ConstCounter::new(value).encode(encoder.encode_descriptor(name, help, None, MetricType::Counter)?)
}

/// A counter with one series per `label` value; left out, as an empty family is, when there is none.
fn counters<N: EncodeCounterValue + Copy>(
    encoder: &mut DescriptorEncoder,
    name: &str,
    help: &str,
    label: &str,
    series: &[(&str, N)],
) -> fmt::Result {
    if series.is_empty() {
        return Ok(());
    }
    let mut family = encoder.encode_descriptor(name, help, None, MetricType::Counter)?;
    for (value, n) in series {
        ConstCounter::new(*n).encode(family.encode_family(&[(label, *value)])?)?;
    }
    Ok(())
}

impl Collector for ReadAtScrape {
    fn encode(&self, mut encoder: DescriptorEncoder) -> fmt::Result {
        let Some(source) = self.0.upgrade() else { return Ok(()) };
        let h = source.holdings();
        let pool = source.pool();
        let e = &mut encoder;
        gauge(e, "maps", "Maps loaded", h.maps)?;
        gauge(e, "maps_held_back", "Maps that failed to load", h.held_back)?;
        gauge(e, "keyframes", "Keyframes in all maps", h.keyframes)?;
        gauge(e, "landmarks", "Landmarks in all maps", h.landmarks)?;
        gauge(e, "observations", "Live observations in all maps", h.observations)?;
        gauge(e, "pool_queued", "Requests waiting for a CPU worker", pool.queued.load(Ordering::Relaxed))?;
        gauge(e, "pool_running", "Requests running on CPU workers", pool.running.load(Ordering::Relaxed))?;
        counter(
            e,
            "pool_rejected",
            "Requests refused because the queue was full",
            pool.rejected.load(Ordering::Relaxed) as u64,
        )?;
        gauge(e, "map_cache_bytes", "Estimated memory of the loaded maps", h.loaded_bytes)?;
        counters(
            e,
            "map_cache_events",
            "Map cache: hit, miss, load, eviction, check (freshness), change (found changed), check_error, log_cut \
             (a load cut bytes off the end of a map's log: see GetMap's load_note)",
            "event",
            &h.cache_events,
        )?;
        counter(e, "map_cache_load_seconds", "Time spent loading maps", h.cache_load_seconds)?;
        let calls: Vec<_> = h.storage.iter().map(|op| (op.operation, op.calls)).collect();
        counters(e, "object_storage_requests", "Object storage calls by operation", "operation", &calls)?;
        let errors: Vec<_> = h.storage.iter().map(|op| (op.operation, op.errors)).collect();
        counters(
            e,
            "object_storage_errors",
            "Object storage calls that failed (not found, not modified and failed conditions are answers, not failures)",
            "operation",
            &errors,
        )?;
        let seconds: Vec<_> = h.storage.iter().map(|op| (op.operation, op.seconds)).collect();
        counters(e, "object_storage_seconds", "Time in object storage calls", "operation", &seconds)
    }
}

/// The service's metrics.
pub struct Metrics {
    registry: Mutex<Registry>,
    requests: Family<RequestLabels, Counter>,
    latency: Family<RouteLabels, Histogram, fn() -> Histogram>,
    stages: Family<StageLabels, Histogram, fn() -> Histogram>,
    body_bytes: Family<TransportLabels, Counter>,
}

impl Metrics {
    /// The metrics counted here, and those read from `source` at each scrape.
    pub fn new(source: Weak<dyn Source>) -> Self {
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
        registry.register_collector(Box::new(ReadAtScrape(source)));
        Self { registry: Mutex::new(registry), requests, latency, stages, body_bytes }
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

    /// The text exposition.
    pub fn render(&self) -> String {
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

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use super::*;

    struct Fixed(PoolStats);

    impl Source for Fixed {
        fn holdings(&self) -> Holdings {
            Holdings {
                maps: 2,
                keyframes: 7,
                loaded_bytes: 1 << 20,
                cache_events: vec![("hit", 3), ("log_cut", 1)],
                cache_load_seconds: 0.5,
                ..Holdings::default()
            }
        }

        fn pool(&self) -> &PoolStats {
            &self.0
        }
    }

    #[test]
    fn values_kept_elsewhere_are_read_at_each_scrape() {
        let source = Arc::new(Fixed(PoolStats::default()));
        let weak: Weak<dyn Source> = Arc::downgrade(&source) as Weak<Fixed>;
        let metrics = Metrics::new(weak);
        source.0.rejected.store(4, Ordering::Relaxed);
        let text = metrics.render();
        for line in [
            "# TYPE scone_pool_rejected counter",
            "scone_pool_rejected_total 4",
            "# TYPE scone_maps gauge",
            "scone_maps 2",
            "scone_keyframes 7",
            "scone_pool_queued 0",
            "scone_map_cache_bytes 1048576",
            "scone_map_cache_events_total{event=\"hit\"} 3",
            "scone_map_cache_events_total{event=\"log_cut\"} 1",
            "scone_map_cache_load_seconds_total 0.5",
        ] {
            assert!(text.lines().any(|l| l == line), "'{line}' is not in\n{text}");
        }
        assert!(!text.contains("object_storage"), "no storage calls, no storage series:\n{text}");
        source.0.rejected.store(5, Ordering::Relaxed);
        assert!(metrics.render().lines().any(|l| l == "scone_pool_rejected_total 5"));
        drop(source);
        assert!(!metrics.render().contains("scone_maps"));
    }
}
