"""Training, export and evaluation of the SConE network (Python + PyTorch).

Run from `training/` as `python -m scone_train.<module>`. The entry points are `train` (one config) and
`release` (the constellation model's whole recipe, behind `scripts/train`); the rest is grouped by what it is
about: `data` (scenes, feature exports, splits, renders and warps, labels, training units), `model` (the networks
and what is made from a trained one), `evaluation` (how a model is scored) and `figures` (the pictures of
docs/figures/). `paths` says where the repository, the `scone` binary and the prefix are.
"""
