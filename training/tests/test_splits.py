"""Tests of the real training scenes' split (scone_train.data.splits): the shipped recipe's five scenes are what
`real_split: true` names, the nine add the four orbits, and no scene's training part shares a frame with its
selection part (by the frame specs alone, so the tests run without the shared data)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from scone_train.data import splits  # noqa: E402


def test_true_names_the_shipped_five_and_nine_adds_the_orbits():
    assert splits.scene_set(True) is splits.SPLIT
    assert list(splits.scene_set("five")) == list(splits.SPLIT)
    nine = splits.scene_set("nine")
    assert list(nine) == list(splits.SPLIT) + list(splits.ORBITS)
    with pytest.raises(ValueError, match="real_split"):
        splits.scene_set("ten")


@pytest.mark.parametrize("name", list(splits.SCENE_SETS["nine"]))
def test_training_and_selection_parts_are_apart(name):
    spec = splits.SCENE_SETS["nine"][name]
    # Stamps 0..999 stand for any scene's frames: the specs name stamps, not positions.
    stamps = [str(i) for i in range(1000)]
    train, select = set(splits.frames(spec["train"], stamps)), set(splits.frames(spec["select"], stamps))
    assert train and select and not train & select


def test_orbit_selection_arcs_keep_a_gap_from_their_training_parts():
    stamps = [f"{i:03d}" for i in range(100)]
    for name in ("llff-ethiopianhead", "llff-lemontea-office", "turntable-squirrel"):
        spec = splits.ORBITS[name]
        train, select = splits.frames(spec["train"], stamps), splits.frames(spec["select"], stamps)
        assert min(select) - max(i for i in train if i < min(select)) >= 3, name
