//! Nearest-neighbour search over a map's observation embeddings: exact below a size threshold, `hnsw_rs`
//! above it.
//!
//! The index stores observation ids (positions in [`MapData::observations`]); removed keyframes leave
//! tombstones (`live = false`) that are filtered at query time, since HNSW cannot delete points. When
//! tombstones exceed `rebuild_dead_share` of the points the graph is rebuilt from the live observations.
//!
//! Persistence: `hnsw_rs`'s dump (graph + data files) plus `index.json` with the number of points, the model
//! id and CRC-32s of both files. A restart loads the dump when it matches and inserts only the observations
//! added after it; anything else (missing, wrong model, checksum mismatch) rebuilds from the map data.
//! Building is the slow part (11-18 s for 100k observations on this machine, `cargo bench --bench replica`), so a dump is written at compaction
//! and at shutdown.

use std::path::Path;

use hnsw_rs::prelude::{AnnT, DistL2, Hnsw, HnswIo};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::error::MapError;
use crate::map::model::MapData;

/// Settings of the index.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct IndexParams {
    /// Below this many observations the search is exact (brute force).
    pub exact_below: usize,
    /// HNSW links per node.
    pub m: usize,
    pub ef_construction: usize,
    pub ef_search: usize,
    /// Rebuild when this share of indexed points are tombstones.
    pub rebuild_dead_share: f64,
}

impl Default for IndexParams {
    fn default() -> Self {
        Self { exact_below: 1_000, m: 16, ef_construction: 100, ef_search: 16, rebuild_dead_share: 0.3 }
    }
}

/// hnsw_rs's dump only reloads with 16 layers.
const MAX_LAYER: usize = 16;

#[derive(Debug, Serialize, Deserialize, PartialEq)]
struct DumpManifest {
    points: usize,
    in_graph: usize,
    model_id: String,
    graph_crc: u32,
    data_crc: u32,
}

/// A neighbour: observation id and L2 distance.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    pub observation: usize,
    pub distance: f32,
}

/// The index of one map.
pub struct EmbeddingIndex {
    params: IndexParams,
    hnsw: Option<Hnsw<'static, f32, DistL2>>,
    /// Observations [0, indexed) are in `hnsw` (when it exists)...
    indexed: usize,
    /// ...of which this many were live when inserted (points in the graph).
    in_graph: usize,
    /// Whether the graph came from a dump (rather than being built here).
    from_dump: bool,
    /// Points in the graph whose keyframe was removed since (tombstones).
    dead_in_graph: usize,
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
    pub fn new(params: IndexParams) -> Self {
        Self { params, hnsw: None, indexed: 0, in_graph: 0, from_dump: false, dead_in_graph: 0 }
    }

    pub fn params(&self) -> &IndexParams {
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
    }

    /// Brings the index up to date with `data` (new observations; a rebuild when there are too many
    /// tombstones; the switch to HNSW when the map outgrows the exact threshold).
    pub fn sync(&mut self, data: &MapData) {
        let total = data.observations.len();
        if total < self.params.exact_below {
            self.hnsw = None;
            self.indexed = total;
            self.in_graph = 0;
            self.dead_in_graph = 0;
            return;
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
            if points.len() > 64 {
                graph.parallel_insert_slice(&points);
            } else {
                for p in points {
                    graph.insert_slice(p);
                }
            }
        }
        self.indexed = total;
    }

    /// The k nearest live observations to `query` that `accept` admits.
    pub fn search(&self, data: &MapData, query: &[f32], k: usize, accept: Accept) -> Vec<Hit> {
        let Some(graph) = &self.hnsw else {
            return exact_search(data, query, k, accept);
        };
        let ef = self.params.ef_search.max(k);
        // hnsw_rs's filtered search is markedly slower: search unfiltered when nothing should be left out, and
        // fall back to the filter if a tombstone shows up anyway (e.g. a removal not yet synced).
        let admit = |id: usize| data.observations.get(id).is_some_and(|o| o.live) && accept.is_none_or(|a| a(id));
        let filter = |id: &usize| admit(*id);
        let found = if accept.is_none() && self.dead_in_graph == 0 {
            let found = graph.search(query, k, ef);
            if found.iter().all(|n| admit(n.d_id)) {
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
    /// searches are independent, and a relocalisation has ~1,500 of them.
    pub fn search_many(&self, data: &MapData, queries: &[f32], k: usize, accept: Accept) -> Vec<Vec<Hit>> {
        let dim = data.meta.dim;
        queries.par_chunks_exact(dim).with_min_len(64).map(|q| self.search(data, q, k, accept)).collect()
    }

    /// Writes the HNSW graph (if any) with a manifest into `dir`.
    pub fn dump(&self, dir: &Path, model_id: &str) -> Result<(), MapError> {
        let manifest_path = dir.join("index.json");
        let Some(graph) = &self.hnsw else {
            let _ = std::fs::remove_file(&manifest_path);
            return Ok(());
        };
        let _ = std::fs::remove_file(&manifest_path);
        let base = "index";
        graph
            .file_dump(dir, base)
            .map_err(|e| MapError::Io { path: dir.join(base), source: std::io::Error::other(e.to_string()) })?;
        let crc = |name: &str| -> Result<u32, MapError> {
            let p = dir.join(name);
            let bytes = std::fs::read(&p).map_err(|source| MapError::Io { path: p.clone(), source })?;
            Ok(crc32fast::hash(&bytes))
        };
        let manifest = DumpManifest {
            points: self.indexed,
            in_graph: self.in_graph,
            model_id: model_id.to_string(),
            graph_crc: crc("index.hnsw.graph")?,
            data_crc: crc("index.hnsw.data")?,
        };
        let json = serde_json::to_vec(&manifest).expect("manifest serialises");
        crate::map::format::write_atomic(&manifest_path, &json)
    }

    /// Loads a dump from `dir` when it matches `data` (model, size, checksums); then syncs the rest.
    /// Returns whether the dump was used.
    pub fn load_or_build(params: IndexParams, dir: &Path, data: &MapData) -> Self {
        let mut index = Self::new(params);
        if let Some((graph, points, in_graph)) = Self::try_load(dir, data) {
            index.hnsw = Some(graph);
            index.indexed = points;
            index.in_graph = in_graph;
            index.from_dump = true;
        }
        index.sync(data);
        index
    }

    fn try_load(dir: &Path, data: &MapData) -> Option<(Hnsw<'static, f32, DistL2>, usize, usize)> {
        let manifest: DumpManifest = serde_json::from_slice(&std::fs::read(dir.join("index.json")).ok()?).ok()?;
        if manifest.model_id != data.meta.model_id || manifest.points > data.observations.len() {
            return None;
        }
        let crc = |name: &str| std::fs::read(dir.join(name)).ok().map(|b| crc32fast::hash(&b));
        if crc("index.hnsw.graph")? != manifest.graph_crc || crc("index.hnsw.data")? != manifest.data_crc {
            tracing::warn!(dir = %dir.display(), "index dump checksum mismatch: rebuilding");
            return None;
        }
        // The loader borrows from its HnswIo for the graph's lifetime; one small HnswIo per load is kept.
        let io: &'static mut HnswIo = Box::leak(Box::new(HnswIo::new(dir, "index")));
        let graph: Hnsw<'static, f32, DistL2> = io.load_hnsw().ok()?;
        Some((graph, manifest.points, manifest.in_graph))
    }
}
