"""How a model is scored: nearest-neighbour precision, the pair protocol on the selection split and on the
validation scenes, the accuracy gate of a faster model, onnxruntime timings, and where the correct matches lie."""
