//! Nearest-neighbour search over a map's observation embeddings: exact below a size threshold, `hnsw_rs`
//! above it.
//!
//! The index stores observation ids (positions in [`MapData::observations`]); removed keyframes leave
//! tombstones (`live = false`) that are filtered at query time, since HNSW cannot delete points. When
//! tombstones exceed `rebuild_dead_share` of the points the graph is rebuilt from the live observations.
//!
//! What the graph's points are is a setting ([`IndexSettings::points`]): one representative view per landmark
//! (the default), or every live observation. A real map has ~2.5 views per landmark, so the first takes ~0.4
//! of the points, and of the graph's memory, build and reload time. A representative is chosen again when its landmark's
//! live views reach a power of two or its keyframe is removed; the point it replaces stays in the graph as a
//! tombstone does, and counts toward the rebuild. The representatives are recorded in the dump's manifest.
//!
//! Persistence: `hnsw_rs`'s dump (a graph and a data file under one base name) plus `index.json`, which
//! names that base and records the model id, CRC-32s of both files, how many observations were offered to
//! the graph and how many it holds, and a CRC-32 of their embeddings. Each dump goes under a new base name
//! (hnsw_rs will not overwrite the files a loaded graph came from, and picks another name itself: the name it
//! returns is the one recorded); the manifest is replaced atomically, and only then are the replaced files
//! deleted. A restart loads the dump only when it holds exactly the map's observations: the manifest matches
//! the map (model, counts, embeddings), the files match their checksums, and, point by point, the graph holds
//! each observation it should with the map's embedding. It then inserts only the observations added after
//! it; anything else rebuilds from the map data. Building is the slow part (11-18 s for 100k observations on
//! this machine, `cargo bench --bench replica`), so a dump is written at compaction and at shutdown.

use std::path::Path;

use hnsw_rs::prelude::{AnnT, DistL2, Hnsw, HnswIo};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::error::MapError;
use std::collections::{BTreeSet, HashMap};

pub use crate::map::model::IndexPoints;
use crate::map::model::{Landmark, MapData};
use crate::map::storage::format::{
    file_crc, io_error, remove_dump, remove_dumps_except, valid_base, DumpManifest, DATA_SUFFIX, DUMP_MANIFEST,
    GRAPH_SUFFIX,
};

/// Settings of the index.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct IndexSettings {
    /// Below this many observations the search is exact (brute force).
    pub exact_below: usize,
    /// HNSW links per node.
    pub m: usize,
    pub ef_construction: usize,
    pub ef_search: usize,
    /// Rebuild when this share of indexed points are tombstones (or, with one point per landmark, points a
    /// landmark's newer representative replaced).
    pub rebuild_dead_share: f64,
    /// What the graph's points are: every observation, or one representative view per landmark.
    pub points: IndexPoints,
}

impl Default for IndexSettings {
    fn default() -> Self {
        Self {
            exact_below: 1_000,
            m: 16,
            ef_construction: 100,
            ef_search: 16,
            rebuild_dead_share: 0.3,
            points: IndexPoints::Landmarks,
        }
    }
}

/// The medoid of a landmark's live views among observations `[0, limit)`: the one with the least summed
/// distance to the others, the first of equals (so of two views, the older).
fn medoid(data: &MapData, landmark: &Landmark, limit: usize) -> Option<usize> {
    let views: Vec<usize> =
        landmark.observations.iter().map(|&o| o as usize).filter(|&o| o < limit && data.observations[o].live).collect();
    if views.len() <= 2 {
        return views.first().copied();
    }
    let cost =
        |i: usize| -> f32 { views.iter().map(|&j| l2_squared(data.embedding(i), data.embedding(j)).sqrt()).sum() };
    views.iter().map(|&v| (cost(v), v)).min_by(|a, b| a.0.total_cmp(&b.0)).map(|(_, v)| v)
}

/// Adds points to a graph: in parallel when there are many, one by one otherwise.
fn insert_points(graph: &Hnsw<'static, f32, DistL2>, points: Vec<(&[f32], usize)>) {
    if points.len() > 64 {
        graph.parallel_insert_slice(&points);
    } else {
        for p in points {
            graph.insert_slice(p);
        }
    }
}

/// Live views of a landmark among observations `[0, limit)`.
fn live_views(data: &MapData, landmark: &Landmark, limit: usize) -> usize {
    landmark.observations.iter().filter(|&&o| (o as usize) < limit && data.observations[o as usize].live).count()
}

/// Extra neighbours an unfiltered search asks for, so that a few points that may not be results (tombstones,
/// replaced representatives) do not force a filtered search.
const SEARCH_SLACK: usize = 2;
/// The fewest searches [`EmbeddingIndex::search_many`] gives one thread (not 64, which left a capped stage 1's
/// 100 searches on one thread).
const SEARCH_CHUNK: usize = 16;

/// Memory of one point of the graph beyond its vector: hnsw_rs's node (16 preallocated layer lists, two `Arc`s)
/// and its links (each its own `Arc`, ~40 bytes with its pointer, 20-23 per point at m = 16), with what the
/// allocator keeps of a reload. Calibrated against the RSS of the reloc bench's 728k-observation map opened
/// from its dump, one point per landmark: 3,300 B under glibc's allocator (1.50 against 1.44-1.45 KB/obs of
/// RSS at 728k), 2,800 B since the crate allocates through mimalloc, which keeps no header beside each small
/// allocation (1.32 against 1.33 KB/obs; BENCHMARKS.md, "mimalloc"). Smaller maps' RSS under mimalloc depends
/// on what it still holds of maps freed before them, so the larger map calibrates.
const GRAPH_POINT_BYTES: usize = 2_800;
/// A landmark's entry in the representatives' map.
const REPRESENTATIVE_BYTES: usize = 32;

/// hnsw_rs's dump only reloads with 16 layers.
const MAX_LAYER: usize = 16;

/// A neighbour: observation id and L2 distance.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    pub observation: usize,
    pub distance: f32,
}

/// The index of one map.
pub struct EmbeddingIndex {
    params: IndexSettings,
    hnsw: Option<Hnsw<'static, f32, DistL2>>,
    /// Observations [0, indexed) are in `hnsw` (when it exists)...
    indexed: usize,
    /// ...of which this many were live when inserted (points in the graph).
    in_graph: usize,
    /// Whether the graph came from a dump (rather than being built here).
    from_dump: bool,
    /// Points in the graph whose keyframe was removed since (tombstones), or, with one point per landmark,
    /// that no longer stand for their landmark.
    dead_in_graph: usize,
    /// With one point per landmark: landmark -> the observation that stands for it...
    representatives: HashMap<u64, usize>,
    /// ...which observations are points of the graph (by id)...
    in_graph_ids: Vec<bool>,
    /// ...and how many observations below `indexed` were live at the last sync (fewer now: a removal).
    live_indexed: usize,
}

impl std::fmt::Debug for EmbeddingIndex {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("EmbeddingIndex").field("hnsw", &self.hnsw.is_some()).field("indexed", &self.indexed).finish()
    }
}

/// Squared L2 distance; written over fixed chunks so the compiler vectorises it.
#[inline]
pub fn l2_squared(a: &[f32], b: &[f32]) -> f32 {
    let mut acc = [0.0f32; 8];
    let chunks = a.len() / 8;
    for c in 0..chunks {
        for l in 0..8 {
            let d = a[c * 8 + l] - b[c * 8 + l];
            acc[l] += d * d;
        }
    }
    let mut s: f32 = acc.iter().sum();
    for i in chunks * 8..a.len() {
        let d = a[i] - b[i];
        s += d * d;
    }
    s
}

/// A restriction on which observations a search may return (e.g. a pose prior); `None` admits all.
pub type Accept<'a> = Option<&'a (dyn Fn(usize) -> bool + Sync)>;

/// Exact k nearest live observations (brute force over the flat embedding array).
pub fn exact_search(data: &MapData, query: &[f32], k: usize, accept: Accept) -> Vec<Hit> {
    let dim = data.meta.dim;
    let mut best: Vec<(f32, usize)> = Vec::with_capacity(k + 1);
    for (i, e) in data.embeddings.chunks_exact(dim).enumerate() {
        let d = l2_squared(query, e);
        if best.len() == k && d >= best[k - 1].0 {
            continue;
        }
        if !data.observations[i].live || accept.is_some_and(|a| !a(i)) {
            continue;
        }
        let pos = best.partition_point(|b| b.0 <= d);
        best.insert(pos, (d, i));
        best.truncate(k);
    }
    best.into_iter().map(|(d, i)| Hit { observation: i, distance: d.sqrt() }).collect()
}

impl EmbeddingIndex {
    pub fn new(params: IndexSettings) -> Self {
        Self {
            params,
            hnsw: None,
            indexed: 0,
            in_graph: 0,
            from_dump: false,
            dead_in_graph: 0,
            representatives: HashMap::new(),
            in_graph_ids: Vec::new(),
            live_indexed: 0,
        }
    }

    pub fn params(&self) -> &IndexSettings {
        &self.params
    }

    /// Changes the search breadth (benchmarks sweep it on one built graph).
    pub fn set_ef_search(&mut self, ef: usize) {
        self.params.ef_search = ef;
    }

    /// Whether the graph was loaded from a dump (true) or built from the map data.
    pub fn loaded_from_dump(&self) -> bool {
        self.from_dump && self.hnsw.is_some()
    }

    /// Points of the HNSW graph and links between them over all layers (`None` without a graph): what the
    /// graph's memory scales with (benchmarks).
    pub fn graph_shape(&self) -> Option<(usize, usize)> {
        let graph = self.hnsw.as_ref()?;
        let (mut points, mut links) = (0usize, 0usize);
        for p in graph.get_point_indexation() {
            points += 1;
            links += p.get_neighborhood_id().iter().map(Vec::len).sum::<usize>();
        }
        Some((points, links))
    }

    /// Every point of the graph with its links, by origin id. For tests that a reloaded graph is the one
    /// dumped.
    #[cfg(test)]
    pub(crate) fn graph_links(&self) -> Vec<(usize, PointLinks)> {
        let Some(graph) = self.hnsw.as_ref() else { return Vec::new() };
        let lists = |p: &hnsw_rs::prelude::Point<'_, f32>| {
            p.get_neighborhood_id().iter().map(|l| l.iter().map(|n| (n.d_id, n.distance)).collect()).collect()
        };
        let mut out: Vec<_> =
            graph.get_point_indexation().into_iter().map(|p| (p.get_origin_id(), lists(&p))).collect();
        out.sort_by_key(|(o, _)| *o);
        out
    }

    /// An estimate of the graph's memory (0 below the exact threshold, where there is none): per point in the
    /// graph, tombstones and replaced representatives included, hnsw_rs's node with its links and its copy of
    /// the embedding, plus the index's own bookkeeping. The per-point figure is calibrated against the RSS of
    /// a map opened from its dump (`cargo bench --bench reloc`).
    pub fn memory_bytes(&self, dim: usize) -> usize {
        if self.hnsw.is_none() {
            return 0;
        }
        self.in_graph * (GRAPH_POINT_BYTES + dim * 4)
            + self.in_graph_ids.len()
            + self.representatives.len() * REPRESENTATIVE_BYTES
    }

    /// Whether queries go through HNSW.
    pub fn is_approximate(&self) -> bool {
        self.hnsw.is_some()
    }

    fn new_graph(&self, expected: usize) -> Hnsw<'static, f32, DistL2> {
        Hnsw::new(self.params.m, expected.max(1024), MAX_LAYER, self.params.ef_construction, DistL2 {})
    }

    /// Forgets the graph, so the next `sync` rebuilds it (after every embedding changed, e.g. a re-embed).
    pub fn reset(&mut self) {
        self.hnsw = None;
        self.indexed = 0;
        self.in_graph = 0;
        self.from_dump = false;
        self.dead_in_graph = 0;
        self.representatives.clear();
        self.in_graph_ids.clear();
        self.live_indexed = 0;
    }

    /// Brings the index up to date with `data` (new observations; a rebuild when there are too many
    /// tombstones; the switch to HNSW when the map outgrows the exact threshold).
    pub fn sync(&mut self, data: &MapData) {
        let total = data.observations.len();
        if total < self.params.exact_below {
            self.reset();
            self.indexed = total;
            return;
        }
        if self.params.points == IndexPoints::Landmarks {
            return self.sync_landmarks(data);
        }
        // Points in the graph whose keyframe has since been removed.
        let live_indexed = data.observations[..self.indexed.min(total)].iter().filter(|o| o.live).count();
        let dead_in_graph = self.in_graph.saturating_sub(live_indexed);
        let rebuild = self.hnsw.is_none()
            || self.indexed > total
            || dead_in_graph as f64 > self.params.rebuild_dead_share * self.in_graph.max(1) as f64;
        if rebuild {
            let graph = self.new_graph(total);
            let points: Vec<(&[f32], usize)> =
                (0..total).filter(|&i| data.observations[i].live).map(|i| (data.embedding(i), i)).collect();
            graph.parallel_insert_slice(&points);
            self.from_dump = false;
            self.in_graph = points.len();
            self.hnsw = Some(graph);
            self.indexed = total;
            self.dead_in_graph = 0;
            return;
        }
        self.dead_in_graph = dead_in_graph;
        if let Some(graph) = &self.hnsw {
            let points: Vec<(&[f32], usize)> =
                (self.indexed..total).filter(|&i| data.observations[i].live).map(|i| (data.embedding(i), i)).collect();
            self.in_graph += points.len();
            insert_points(graph, points);
        }
        self.indexed = total;
    }

    /// [`EmbeddingIndex::sync`] with one point per landmark ([`IndexPoints::Landmarks`]).
    fn sync_landmarks(&mut self, data: &MapData) {
        let total = data.observations.len();
        let live_before = data.observations[..self.indexed.min(total)].iter().filter(|o| o.live).count();
        let live_now = live_before + data.observations[self.indexed.min(total)..].iter().filter(|o| o.live).count();
        let replaced = self.in_graph.saturating_sub(self.representatives.len());
        let rebuild = self.hnsw.is_none()
            || self.indexed > total
            || replaced as f64 > self.params.rebuild_dead_share * self.in_graph.max(1) as f64;
        if rebuild {
            let mut ids: Vec<usize> = data.landmarks.par_iter().filter_map(|(_, l)| medoid(data, l, total)).collect();
            ids.sort_unstable();
            let graph = self.new_graph(ids.len());
            let points: Vec<(&[f32], usize)> = ids.iter().map(|&i| (data.embedding(i), i)).collect();
            graph.parallel_insert_slice(&points);
            self.in_graph_ids = vec![false; total];
            for &i in &ids {
                self.in_graph_ids[i] = true;
            }
            self.representatives = ids.iter().map(|&i| (data.observations[i].landmark, i)).collect();
            self.in_graph = ids.len();
            self.hnsw = Some(graph);
            self.from_dump = false;
            self.indexed = total;
            self.live_indexed = live_now;
            self.dead_in_graph = 0;
            return;
        }
        // Landmarks whose representative may change: those with new views, and, after a removal, those whose
        // representative's keyframe went.
        let mut touched: BTreeSet<u64> =
            data.observations[self.indexed..total].iter().filter(|o| o.live).map(|o| o.landmark).collect();
        if live_before < self.live_indexed {
            touched.extend(self.representatives.iter().filter(|(_, &o)| !data.observations[o].live).map(|(&l, _)| l));
        }
        let mut inserts = Vec::new();
        for lm in touched {
            let current = self.representatives.get(&lm).copied();
            let Some(l) = data.landmarks.get(&lm) else {
                self.representatives.remove(&lm);
                continue;
            };
            if current.is_some_and(|o| data.observations[o].live) {
                // Chosen again only when its live views reach a power of two.
                let (before, after) = (live_views(data, l, self.indexed), live_views(data, l, total));
                let reached = after.checked_ilog2().is_some_and(|p| (1usize << p) > before);
                if !reached {
                    continue;
                }
            }
            match medoid(data, l, total) {
                Some(n) if Some(n) != current => {
                    self.representatives.insert(lm, n);
                    inserts.push(n);
                }
                Some(_) => {}
                None => {
                    self.representatives.remove(&lm);
                }
            }
        }
        self.in_graph_ids.resize(total, false);
        inserts.retain(|&i| !std::mem::replace(&mut self.in_graph_ids[i], true));
        inserts.sort_unstable();
        if let Some(graph) = &self.hnsw {
            insert_points(graph, inserts.iter().map(|&i| (data.embedding(i), i)).collect());
        }
        self.in_graph += inserts.len();
        self.indexed = total;
        self.live_indexed = live_now;
        self.dead_in_graph = self.in_graph.saturating_sub(self.representatives.len());
    }

    /// Whether observation `id` may be a search result (before the caller's own restriction): live, and,
    /// with one point per landmark, its landmark's representative.
    pub fn admissible(&self, data: &MapData, id: usize) -> bool {
        data.observations.get(id).is_some_and(|o| {
            o.live
                && (self.params.points == IndexPoints::Observations
                    || self.representatives.get(&o.landmark) == Some(&id))
        })
    }

    /// The k nearest live observations to `query` that `accept` admits.
    pub fn search(&self, data: &MapData, query: &[f32], k: usize, accept: Accept) -> Vec<Hit> {
        let Some(graph) = &self.hnsw else {
            return exact_search(data, query, k, accept);
        };
        let ef = self.params.ef_search.max(k + SEARCH_SLACK);
        // hnsw_rs's filtered search is markedly slower: without the caller's restriction, search unfiltered for
        // a few more than k and pass over the points that may not be results (tombstones, replaced
        // representatives); only when fewer than k remain, search again with the filter.
        let admit = |id: usize| self.admissible(data, id) && accept.is_none_or(|a| a(id));
        let filter = |id: &usize| admit(*id);
        let found = if accept.is_none() {
            let mut found = graph.search(query, k + SEARCH_SLACK, ef);
            found.retain(|n| admit(n.d_id));
            if found.len() >= k {
                found.truncate(k);
                found
            } else {
                graph.search_filter(query, k, ef, Some(&filter))
            }
        } else {
            graph.search_filter(query, k, ef, Some(&filter))
        };
        let mut hits: Vec<Hit> = found.into_iter().map(|n| Hit { observation: n.d_id, distance: n.distance }).collect();
        // Observations added since the last sync are searched exactly.
        for i in self.indexed..data.observations.len() {
            if data.observations[i].live && accept.is_none_or(|a| a(i)) {
                hits.push(Hit { observation: i, distance: l2_squared(query, data.embedding(i)).sqrt() });
            }
        }
        hits.sort_by(|a, b| a.distance.total_cmp(&b.distance));
        hits.truncate(k);
        hits
    }

    /// [`EmbeddingIndex::search`] for every row of `queries` (`[n, dim]`), spread over rayon's threads: the
    /// searches are independent. A relocalisation's capped stage 1 has 100 of them and its fallback ~2,000;
    /// chunks of `SEARCH_CHUNK` (16) let the 100 use every thread too (each search takes 30-130 µs on the
    /// bench maps, far more than a split costs).
    pub fn search_many(&self, data: &MapData, queries: &[f32], k: usize, accept: Accept) -> Vec<Vec<Hit>> {
        let dim = data.meta.dim;
        queries.par_chunks_exact(dim).with_min_len(SEARCH_CHUNK).map(|q| self.search(data, q, k, accept)).collect()
    }

    /// Writes the HNSW graph (if any) of `data` with its manifest into `dir`: hnsw_rs's two files under a
    /// new base name, then `index.json` naming them (atomically), then the dumps it replaces are deleted. A
    /// failed dump removes its partial files and leaves the previous dump (and its manifest) as they were.
    /// Without a graph, every dump in `dir` is removed. Fail point `index-dump`.
    pub fn dump(&self, dir: &Path, data: &MapData) -> Result<(), MapError> {
        let manifest_path = dir.join(DUMP_MANIFEST);
        let Some(graph) = &self.hnsw else {
            let _ = std::fs::remove_file(&manifest_path);
            remove_dumps_except(dir, None);
            return Ok(());
        };
        let base = format!("index-{:016x}", rand::random::<u64>());
        let written = if crate::map::storage::format::injected("index-dump", dir) {
            let _ = std::fs::write(dir.join(format!("{base}{GRAPH_SUFFIX}")), b"partial");
            Err(crate::map::storage::format::injected_full(&dir.join(&base)))
        } else {
            // hnsw_rs panics on some I/O failures (a file it cannot create): a failed dump, not a crash.
            let dumped = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| graph.file_dump(dir, &base)));
            match dumped {
                Ok(Ok(name)) => Ok(name),
                Ok(Err(e)) => {
                    let kind = e
                        .chain()
                        .find_map(|c| c.downcast_ref::<std::io::Error>())
                        .map_or(std::io::ErrorKind::Other, std::io::Error::kind);
                    Err(io_error(&dir.join(&base), std::io::Error::new(kind, format!("{e:#}"))))
                }
                Err(_) => Err(io_error(&dir.join(&base), std::io::Error::other("hnsw_rs panicked while dumping"))),
            }
        };
        let name = match written {
            Ok(name) => name,
            Err(e) => {
                remove_dump(dir, &base);
                return Err(e);
            }
        };
        let finished = (|| {
            let manifest = DumpManifest {
                base: name.clone(),
                points: self.indexed,
                in_graph: self.in_graph,
                model_id: data.meta.model_id.clone(),
                graph_crc: file_crc(&dir.join(format!("{name}{GRAPH_SUFFIX}")))?,
                data_crc: file_crc(&dir.join(format!("{name}{DATA_SUFFIX}")))?,
                embeddings_crc: embeddings_crc(data, self.indexed),
                index_points: self.params.points,
                representatives: {
                    let mut r: Vec<usize> = self.representatives.values().copied().collect();
                    r.sort_unstable();
                    r
                },
            };
            let json = serde_json::to_vec(&manifest).expect("manifest serialises");
            crate::map::storage::format::write_atomic(&manifest_path, &json)
        })();
        if let Err(e) = finished {
            remove_dump(dir, &name);
            return Err(e);
        }
        remove_dumps_except(dir, Some(&name));
        Ok(())
    }

    /// Loads a dump from `dir` when it holds exactly what `data` says it should (model, files' checksums,
    /// the embeddings it was built from, and, point by point, the observations in the graph); then syncs the
    /// rest. Anything else rebuilds from the map data.
    pub fn load_or_build(params: IndexSettings, dir: &Path, data: &MapData) -> Self {
        Self::from_dump(params, dir, data, DumpRead::read(dir, params.points))
    }

    /// [`EmbeddingIndex::load_or_build`] with the dump already read ([`DumpRead::read`], which needs no map
    /// data, so a load can read the graph while it decodes the snapshot): checked against `data`, then synced.
    pub fn from_dump(
        params: IndexSettings,
        dir: &Path,
        data: &MapData,
        read: Result<Option<DumpRead>, String>,
    ) -> Self {
        let mut index = Self::new(params);
        match read.and_then(|r| r.map(|r| r.check(data, params.points)).transpose()) {
            Ok(Some(LoadedDump { graph, points, in_graph, representatives, in_graph_ids })) => {
                index.hnsw = Some(graph);
                index.indexed = points;
                index.in_graph = in_graph;
                index.from_dump = true;
                index.representatives = representatives;
                index.in_graph_ids = in_graph_ids;
                // Unknown until the first sync: it looks for representatives a removal took since the dump.
                index.live_indexed = usize::MAX;
            }
            Ok(None) => {}
            Err(reason) => tracing::warn!(dir = %dir.display(), %reason, "index dump not used: rebuilding"),
        }
        index.sync(data);
        index
    }
}

/// One graph point's links: per layer, the (origin id, distance) of each neighbour in the list's order.
#[cfg(test)]
pub(crate) type PointLinks = Vec<Vec<(usize, f32)>>;

/// A dump read from disk, not yet checked against its map: the manifest and hnsw_rs's graph, its files
/// matching the manifest's checksums.
pub struct DumpRead {
    manifest: DumpManifest,
    graph: Hnsw<'static, f32, DistL2>,
}

impl DumpRead {
    /// Reads the dump in `dir` for an index of `points`: `Ok(None)` when there is none, `Err` with the reason
    /// when it cannot be used.
    pub fn read(dir: &Path, points: IndexPoints) -> Result<Option<Self>, String> {
        let Ok(bytes) = std::fs::read(dir.join(DUMP_MANIFEST)) else { return Ok(None) };
        let manifest: DumpManifest =
            serde_json::from_slice(&bytes).map_err(|e| format!("{DUMP_MANIFEST} does not read: {e}"))?;
        if manifest.index_points != points {
            return Err(format!("dumped with points {:?}, the settings say {points:?}", manifest.index_points));
        }
        if !valid_base(&manifest.base) {
            return Err(format!("names the files '{}'", manifest.base));
        }
        let crc = |suffix: &str| file_crc(&dir.join(format!("{}{suffix}", manifest.base))).ok();
        if crc(GRAPH_SUFFIX) != Some(manifest.graph_crc) || crc(DATA_SUFFIX) != Some(manifest.data_crc) {
            return Err("the files' checksums do not match the manifest".into());
        }
        let load = || {
            // The loader borrows from its HnswIo for the graph's lifetime; one small HnswIo per load is kept.
            let io: &'static mut HnswIo = Box::leak(Box::new(HnswIo::new(dir, &manifest.base)));
            io.load_hnsw()
        };
        // hnsw_rs asserts on what it reads (magic numbers, dimensions): a bad file is a rebuild, not a crash.
        let graph: Hnsw<'static, f32, DistL2> = match std::panic::catch_unwind(std::panic::AssertUnwindSafe(load)) {
            Ok(Ok(g)) => g,
            Ok(Err(e)) => return Err(format!("hnsw_rs cannot load it: {e}")),
            Err(_) => return Err("hnsw_rs panicked loading it".into()),
        };
        Ok(Some(Self { manifest, graph }))
    }

    /// The dump if it holds exactly what `data` says it should, `Err` with the reason otherwise.
    fn check(self, data: &MapData, points: IndexPoints) -> Result<LoadedDump, String> {
        let Self { manifest, graph } = self;
        if manifest.model_id != data.meta.model_id {
            return Err(format!("dumped for model {}", manifest.model_id));
        }
        if manifest.points > data.observations.len() {
            return Err(format!("holds {} observations, the map {}", manifest.points, data.observations.len()));
        }
        if embeddings_crc(data, manifest.points) != manifest.embeddings_crc {
            return Err("built from other embeddings than the map's".into());
        }
        let in_graph_ids = check_graph(&graph, data, &manifest)?;
        let representatives = if points == IndexPoints::Landmarks {
            check_representatives(data, &manifest, &in_graph_ids)?
        } else {
            HashMap::new()
        };
        let in_graph_ids = if points == IndexPoints::Landmarks { in_graph_ids } else { Vec::new() };
        Ok(LoadedDump { graph, points: manifest.points, in_graph: manifest.in_graph, representatives, in_graph_ids })
    }
}

/// A dump that matched its map: the graph, its manifest's counts, and with one point per landmark, the
/// representatives and which observations are points.
struct LoadedDump {
    graph: Hnsw<'static, f32, DistL2>,
    points: usize,
    in_graph: usize,
    representatives: HashMap<u64, usize>,
    in_graph_ids: Vec<bool>,
}

/// The representatives a landmark dump records, checked against the map and the graph: each an observation
/// in the graph, one per landmark, and one for every landmark with a live view in the graph's range (a
/// representative a removal took since the dump is chosen again at the first sync).
fn check_representatives(
    data: &MapData,
    manifest: &DumpManifest,
    in_graph_ids: &[bool],
) -> Result<HashMap<u64, usize>, String> {
    let mut out = HashMap::with_capacity(manifest.representatives.len());
    for &o in &manifest.representatives {
        if !in_graph_ids.get(o).copied().unwrap_or(false) {
            return Err(format!("representative {o} is not in the graph"));
        }
        if out.insert(data.observations[o].landmark, o).is_some() {
            return Err(format!("landmark {} has two representatives", data.observations[o].landmark));
        }
    }
    let points = manifest.points;
    let seen =
        |l: &Landmark| l.observations.iter().any(|&o| (o as usize) < points && data.observations[o as usize].live);
    if let Some((id, _)) = data.landmarks.iter().find(|(id, l)| !out.contains_key(id) && seen(l)) {
        return Err(format!("landmark {id} has no representative"));
    }
    Ok(out)
}

/// CRC-32 of the embeddings of observations `[0, points)`: what the graph was built from.
fn embeddings_crc(data: &MapData, points: usize) -> u32 {
    let mut h = crc32fast::Hasher::new();
    // Little-endian bytes a block at a time: one call per value costs more than the CRC itself.
    let mut bytes = Vec::with_capacity(4 * 4096);
    for block in data.embeddings[..(points * data.meta.dim).min(data.embeddings.len())].chunks(4096) {
        bytes.clear();
        bytes.extend(block.iter().flat_map(|v| v.to_le_bytes()));
        h.update(&bytes);
    }
    h.finalize()
}

/// Whether a loaded graph holds exactly what the map says it should: `in_graph` points, each an observation
/// below `points` (once) with the map's embedding; with one point per observation, also every observation
/// below `points` that is still live (a removed keyframe's observations may stay as tombstones; a live one
/// never went missing). Returns which observations are points.
fn check_graph(
    graph: &Hnsw<'static, f32, DistL2>,
    data: &MapData,
    manifest: &DumpManifest,
) -> Result<Vec<bool>, String> {
    let (points, in_graph) = (manifest.points, manifest.in_graph);
    let mut seen = vec![false; points];
    let mut count = 0usize;
    for p in graph.get_point_indexation() {
        let id = p.get_origin_id();
        if id >= points || seen[id] {
            return Err(format!("observation {id} is out of range or in the graph twice"));
        }
        if p.get_v() != data.embedding(id) {
            return Err(format!("observation {id} has another embedding in the graph"));
        }
        seen[id] = true;
        count += 1;
    }
    if count != in_graph {
        return Err(format!("the graph holds {count} points, the manifest says {in_graph}"));
    }
    if manifest.index_points == IndexPoints::Observations {
        if let Some(missing) = (0..points).find(|&i| data.observations[i].live && !seen[i]) {
            return Err(format!("live observation {missing} is not in the graph"));
        }
    }
    Ok(seen)
}
