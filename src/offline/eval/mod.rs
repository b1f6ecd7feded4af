//! Evaluation on real scenes (the paper's protocol): pair matching with relative pose (`pairs`), and
//! relocalisation against a map (`reloc`), matching under exact homographies (`homography`). Commands:
//! `scone eval pairs --scene DIR`, `scone eval reloc`, `scone eval homography`.

pub mod homography;
pub mod merge;
pub mod methods;
pub mod pairs;
pub mod reloc;
pub mod stats;
