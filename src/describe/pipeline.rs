//! The path every image and every client keypoint set takes: decode -> FAST + FREAK -> context (the ring
//! context sampled from the image, or constellations built from the keypoints) -> SConE embeddings. The service, the commands and the evaluation call this; nothing else strings the stages
//! together. Callers that report stage times pass a [`StageTimes`] for the describer to fill.

use std::sync::{mpsc, Arc};
use std::time::Instant;

use opencv::core::{KeyPoint, Vector};
use parking_lot::Mutex;

use crate::cpu_pool;
use crate::describe::decode::{decode_grey, GreyImage, ImageLimitSettings};
use crate::describe::embedding::{Embedder, Lease, ROW_GROUP};
use crate::describe::features::{self, ExtractorSettings, Features};
use crate::describe::ring_context::RingSampler;
use crate::error::{EmbeddingError, FeatureError};

/// Wall time of each stage of a request, seconds, in order.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct StageTimes(pub Vec<(&'static str, f64)>);

impl StageTimes {
    /// Runs `f` and records its wall time as `stage`.
    pub fn time<R>(&mut self, stage: &'static str, f: impl FnOnce() -> R) -> R {
        let t = Instant::now();
        let r = f();
        self.0.push((stage, t.elapsed().as_secs_f64()));
        r
    }

    /// Adds `other`'s times, summing stages both have (the two frames of a pair).
    pub fn add(&mut self, other: &StageTimes) {
        for (s, t) in &other.0 {
            match self.0.iter_mut().find(|(n, _)| n == s) {
                Some(e) => e.1 += t,
                None => self.0.push((s, *t)),
            }
        }
    }
}

/// SConE embeddings of a feature set (`[N, embedder.dim()]`, row-major): its context (constellations built
/// here, or the ring contexts it carries), then the model.
pub fn embed(embedder: &Embedder, features: &Features) -> Result<Vec<f32>, EmbeddingError> {
    embedder.embed(features)
}

/// FAST + FREAK features of a decoded image, with their ring contexts when `embedder` reads them: what every
/// caller that embeds an image's features extracts ([`Describer::extract`] times the two steps).
pub fn extract_for(
    image: &GreyImage,
    extractor: &ExtractorSettings,
    embedder: &Embedder,
) -> Result<Features, FeatureError> {
    let mut features = features::extract(image, extractor)?;
    if embedder.needs_context() {
        features.sample_context(image)?;
    }
    Ok(features)
}

/// Keypoints from which [`describe_decoded`] overlaps FREAK with the model's work.
pub const PIPELINE_FROM: usize = 512;
/// Keypoints of each FREAK call and of each part the two threads take in turn: a multiple of [`ROW_GROUP`], so
/// the parts' embeddings are the whole set's bit for bit.
const PIECE: usize = 256;
const _: () = assert!(PIECE.is_multiple_of(ROW_GROUP));

/// FAST + FREAK features of a decoded image with their SConE embeddings, timing `extract` (detection and
/// FREAK), `context` and `embed`.
///
/// A ring model's context and embedding of a keypoint depend on that keypoint alone. So on an embedder of
/// several sessions, one of them idle, and with [`PIPELINE_FROM`] keypoints or more, they overlap FREAK:
/// - this thread runs FREAK on the detected keypoints in calls of `PIECE` (256) keypoints, and puts what each
///   call gives on a queue, in parts of `PIECE` rows counted over the whole set;
/// - a scoped thread with a session of its own (one idle as it starts) takes the parts off the queue: it
///   samples their ring contexts and embeds them;
/// - once FREAK is done, this thread takes parts too, on another session if one is idle; parts that no
///   thread took (no session was idle) wait here for one.
///
/// The parts are put back in order, so the features and embeddings are bit for bit what one call of each
/// stage gives (tested): FREAK describes each keypoint alone (the image's integral is made again in each
/// call), the context too, and the model's rows are independent, taken in parts that start on a multiple of
/// [`ROW_GROUP`] rows. Here `extract` is the time until FREAK's last call returns and `embed` the rest; `context` is
/// not timed apart. Otherwise, and for a constellation model (whose context is every keypoint's
/// neighbours), the stages run one after the other.
pub fn describe_decoded(
    image: &GreyImage,
    extractor: &ExtractorSettings,
    embedder: &Embedder,
    times: &mut StageTimes,
) -> Result<Described, DescribeError> {
    let start = Instant::now();
    extractor.validate()?;
    let mut candidates = features::detect(image, extractor)?;
    // A session idle now: the other thread takes it, unless another request takes it first (then the parts
    // wait for this thread).
    let overlap = embedder.needs_context()
        && candidates.len() >= PIPELINE_FROM
        && cpu_pool::cores() > 1
        && embedder.sessions() > 1
        && embedder.try_lease().is_some();
    if !overlap {
        let mut features = features::describe(image, &mut candidates)?;
        times.0.push(("extract", start.elapsed().as_secs_f64()));
        if embedder.needs_context() {
            times.time("context", || features.sample_context(image))?;
        }
        let embeddings = times.time("embed", || embedder.embed(&features))?;
        return Ok(Described { features, embeddings });
    };
    let sampler = RingSampler::new(image)?;
    let (parts, done) = pipelined(image, &candidates, embedder, &sampler, times, start)?;
    let mut features = Features { width: image.width(), height: image.height(), ..Default::default() };
    let mut embeddings = Vec::new();
    for (f, e) in parts {
        features.append(f);
        embeddings.extend(e);
    }
    times.0.push(("embed", done.elapsed().as_secs_f64()));
    Ok(Described { features, embeddings })
}

type Part = (Features, Vec<f32>);

/// [`describe_decoded`]'s two threads: the parts in order, and when FREAK's last call returned.
fn pipelined(
    image: &GreyImage,
    candidates: &Vector<KeyPoint>,
    embedder: &Embedder,
    sampler: &RingSampler,
    times: &mut StageTimes,
    start: Instant,
) -> Result<(Vec<Part>, Instant), DescribeError> {
    let (send, receive) = mpsc::channel::<(usize, Features)>();
    let queue = Mutex::new(receive);
    // Takes parts off the queue until it is closed and empty, each embedded on `lease`.
    let drain = |lease: &mut Lease| -> Result<Vec<(usize, Part)>, DescribeError> {
        let mut out = Vec::new();
        loop {
            // Not in the loop's head: a `while let` would hold the lock through the body.
            let next = queue.lock().recv();
            let Ok((i, mut f)) = next else { break };
            f.sample_context_from(sampler, false);
            let e = lease.embed(&f)?;
            out.push((i, (f, e)));
        }
        Ok(out)
    };
    // Only with a session idle: waiting for one could mean waiting for another request's whole describe.
    let helper = || embedder.try_lease().map_or_else(|| Ok(Vec::new()), |mut lease| drain(&mut lease));
    std::thread::scope(|scope| {
        let other = std::thread::Builder::new().spawn_scoped(scope, helper);
        // Returns how many parts it put on the queue.
        let freak = || -> Result<usize, DescribeError> {
            // FREAK's output so far that is not yet in a part: parts start at multiples of `PIECE` of the whole
            // set whatever FREAK drops, so the model sees the rows in the groups one call would.
            let mut pending = Features { width: image.width(), height: image.height(), ..Default::default() };
            let (mut from, mut index) = (0, 0);
            while from < candidates.len() {
                let to = (from + PIECE).min(candidates.len());
                let mut kps: Vector<KeyPoint> =
                    (from..to).map(|i| candidates.get(i)).collect::<Result<_, _>>().map_err(FeatureError::from)?;
                pending.append(features::describe(image, &mut kps)?);
                from = to;
                let last = from == candidates.len();
                while pending.len() >= PIECE || (last && !pending.is_empty()) {
                    let rest = pending.split_off(PIECE.min(pending.len()));
                    // The receiver lives until the scope ends: the send cannot fail.
                    let _ = send.send((index, std::mem::replace(&mut pending, rest)));
                    index += 1;
                }
            }
            Ok(index)
        };
        let described = freak();
        drop(send);
        let done = Instant::now();
        times.0.push(("extract", (done - start).as_secs_f64()));
        // This thread helps once FREAK is done, on a session idle then (on an error, it empties the queue so
        // the other stops soon).
        let mine = match &described {
            Ok(_) => embedder.try_lease().map_or_else(|| Ok(Vec::new()), |mut own| drain(&mut own)),
            Err(_) => {
                while queue.lock().try_recv().is_ok() {}
                Ok(Vec::new())
            }
        };
        let theirs = match other {
            Ok(t) => t.join().expect("a describe thread panicked"),
            Err(e) => {
                tracing::debug!(error = %e, "no second thread for the describe pipeline");
                Ok(Vec::new())
            }
        };
        let sent = described?;
        let mut parts = mine?;
        parts.extend(theirs?);
        // Parts neither thread took, when neither found a session idle (or there was no second thread): this
        // one waits for a session and embeds them.
        if parts.len() < sent {
            parts.extend(drain(&mut embedder.lease())?);
        }
        parts.sort_unstable_by_key(|(i, _)| *i);
        Ok((parts.into_iter().map(|(_, p)| p).collect(), done))
    })
}

/// Errors of the whole path.
#[derive(Debug, thiserror::Error)]
pub enum DescribeError {
    #[error(transparent)]
    Feature(#[from] FeatureError),
    #[error(transparent)]
    Embedding(#[from] EmbeddingError),
}

/// Features of an image with their SConE embeddings (`[N, dim]`, row-major).
#[derive(Debug, Clone)]
pub struct Described {
    pub features: Features,
    pub embeddings: Vec<f32>,
}

/// Extraction settings, limits and the model, shared by all callers.
#[derive(Debug, Clone)]
pub struct Describer {
    pub extractor: ExtractorSettings,
    pub limits: ImageLimitSettings,
    pub embedder: Arc<Embedder>,
}

impl Describer {
    /// Encoded image -> features and embeddings ([`describe_decoded`]).
    pub fn describe_image(&self, bytes: &[u8]) -> Result<Described, DescribeError> {
        self.describe_timed(bytes, &mut StageTimes::default())
    }

    /// [`Describer::describe_image`], timing `decode` and [`describe_decoded`]'s stages.
    pub fn describe_timed(&self, bytes: &[u8], times: &mut StageTimes) -> Result<Described, DescribeError> {
        let image = times.time("decode", || decode_grey(bytes, &self.limits))?;
        describe_decoded(&image, &self.extractor, &self.embedder, times)
    }

    /// Encoded image -> FAST + FREAK features, with their ring contexts when the model reads them; timing
    /// `decode`, `extract` and `context`.
    pub fn extract(&self, bytes: &[u8], times: &mut StageTimes) -> Result<Features, FeatureError> {
        let image = times.time("decode", || decode_grey(bytes, &self.limits))?;
        let mut features = times.time("extract", || features::extract(&image, &self.extractor))?;
        if self.embedder.needs_context() {
            times.time("context", || features.sample_context(&image))?;
        }
        Ok(features)
    }

    /// Features (extracted here or validated client keypoints) -> embeddings, timing `embed`.
    pub fn embed(&self, features: Features, times: &mut StageTimes) -> Result<Described, EmbeddingError> {
        let embeddings = times.time("embed", || embed(&self.embedder, &features))?;
        Ok(Described { features, embeddings })
    }
}
