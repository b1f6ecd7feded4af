//! Times hnsw_rs's reload of one dump: `reload-timing DIR BASE [ROUNDS]`, each round a fresh load.
use std::time::Instant;

use hnsw_rs::prelude::{DistL2, Hnsw, HnswIo};

#[cfg(feature = "mimalloc")]
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// The process's resident memory, MB.
fn rss_mb() -> f64 {
    let statm = std::fs::read_to_string("/proc/self/statm").expect("procfs");
    statm.split_whitespace().nth(1).and_then(|p| p.parse::<f64>().ok()).expect("statm's second field") * 4096.0 / 1e6
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let (dir, base) = (std::path::PathBuf::from(&args[1]), args[2].clone());
    let rounds: usize = args.get(3).map_or(3, |r| r.parse().expect("ROUNDS is a number"));
    for _ in 0..rounds {
        let t = Instant::now();
        // The loader borrows from its HnswIo for the graph's lifetime, as in the service.
        let io: &'static mut HnswIo = Box::leak(Box::new(HnswIo::new(&dir, &base)));
        let graph: Hnsw<'static, f32, DistL2> = io.load_hnsw().expect("the dump loads");
        let secs = t.elapsed().as_secs_f64();
        let links: usize = graph
            .get_point_indexation()
            .into_iter()
            .map(|p| p.get_neighborhood_id().iter().map(Vec::len).sum::<usize>())
            .sum();
        println!("{} points, {links} links: loaded in {secs:.3} s; RSS {:.0} MB", graph.get_nb_point(), rss_mb());
    }
}
