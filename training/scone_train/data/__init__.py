"""What the network learns from: scenes and the Rust feature exports, the real-data split, rendered sequences and
exact warps, geometry-only labels and the ground truth's residuals, and the training units and samplers."""
