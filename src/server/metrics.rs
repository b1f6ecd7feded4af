//! Prometheus metrics: requests and latency per transport, route and status; time per pipeline stage;
//! maps, keyframes and observations held; the CPU pool's queue. Counts of maps are read at scrape time.

use std::sync::atomic::Ordering;

use parking_lot::Mutex;
use prometheus_client::encoding::text::encode;
use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{exponential_buckets, Histogram};
use prometheus_client::registry::Registry;

use crate::service::{Holdings, StageTimes};
use crate::workers::PoolStats;

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
struct StageLabels {
    stage: String,
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
    maps: Gauge,
    held_back: Gauge,
    keyframes: Gauge,
    landmarks: Gauge,
    observations: Gauge,
    queued: Gauge,
    running: Gauge,
    rejected: Gauge,
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
        Self {
            registry: Mutex::new(registry),
            requests,
            latency,
            stages,
            maps,
            held_back,
            keyframes,
            landmarks,
            observations,
            queued,
            running,
            rejected,
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
        let mut out = String::new();
        if encode(&mut out, &self.registry.lock()).is_err() {
            out.clear();
        }
        out
    }
}
