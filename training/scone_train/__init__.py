"""Training, export and evaluation of the SConE network (Python + PyTorch)."""
