"""The networks, and what is made from a trained one: the ONNX export, an int8 graph, distilled students, and
the golden fixture of the Rust parity test."""
