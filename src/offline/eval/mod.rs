//! Evaluation on real scenes (the paper's protocol): pair matching with relative pose (`pairs`), and
//! relocalisation against a map (later). Commands: `scone eval pairs --scene DIR`.

pub mod merge;
pub mod methods;
pub mod pairs;
pub mod reloc;
pub mod stats;
