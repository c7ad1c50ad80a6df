"""Vocabulary tree: training, transforms, save/load, and place recognition on real images."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import require

from slam.core.errors import InputError
from slam.loop.orb import detect_orb
from slam.loop.training import AugmentOptions, default_training_images, skimage_photos
from slam.loop.vocabulary import (
    Vocabulary,
    default_vocabulary_path,
    l1_score,
    load_default_vocabulary,
)


@pytest.fixture(scope="module")
def small_training_set() -> list[np.ndarray]:
    images = list(default_training_images(AugmentOptions(variants_per_image=2)))[:24]
    return [detect_orb(img, max_features=500).descriptors for img in images]


def test_train_transform_and_round_trip(
    small_training_set: list[np.ndarray], tmp_path: Path
) -> None:
    vocab = Vocabulary.train(small_training_set, branching=6, levels=3, seed=1)
    n_desc = sum(len(d) for d in small_training_set)
    assert 6 < vocab.num_words <= min(6**3, n_desc)
    assert np.all(vocab.idf >= 0)
    probe = small_training_set[3]
    bow = vocab.transform(probe)
    assert np.all(np.diff(bow.word_ids) > 0)
    assert bow.weights.sum() == pytest.approx(1.0, abs=1e-5)
    assert l1_score(bow, bow) == pytest.approx(1.0, abs=1e-5)
    # Each descriptor's word is reached greedily: its leaf is at least as close as any sibling.
    words = vocab.words(probe)
    assert words.min() >= 0 and words.max() < vocab.num_words
    vocab.save(tmp_path / "v.npz")
    loaded = Vocabulary.load(tmp_path / "v.npz")
    np.testing.assert_array_equal(loaded.words(probe), words)
    for d in small_training_set[:5]:
        a, b = vocab.transform(d), loaded.transform(d)
        np.testing.assert_array_equal(a.word_ids, b.word_ids)
        np.testing.assert_array_equal(a.weights, b.weights)
    # Training is deterministic for a seed.
    again = Vocabulary.train(small_training_set, branching=6, levels=3, seed=1)
    np.testing.assert_array_equal(again.node_descriptors, vocab.node_descriptors)


def test_leaf_is_nearest_among_its_siblings(small_training_set: list[np.ndarray]) -> None:
    vocab = Vocabulary.train(small_training_set, branching=5, levels=2, seed=0)
    desc = small_training_set[0][:50]
    leaf_of_word = np.flatnonzero(vocab.node_words >= 0)
    leaves = leaf_of_word[vocab.words(desc)]
    bits = np.unpackbits(desc, axis=1)
    for i, leaf in enumerate(leaves):
        parent = vocab.parents[leaf]
        siblings = vocab.children[parent][vocab.children[parent] >= 0]
        dist = (np.unpackbits(vocab.node_descriptors[siblings], axis=1) != bits[i]).sum(1)
        assert dist[list(siblings).index(leaf)] == dist.min()


def test_load_errors(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="no such"):
        Vocabulary.load(tmp_path / "none.npz")
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError, match="not a vocabulary"):
        Vocabulary.load(tmp_path / "bad.npz")


def test_default_vocabulary_is_shipped_small_and_fast() -> None:
    path = default_vocabulary_path()
    assert path.is_file()
    assert path.stat().st_size < 3.5e6
    vocab = load_default_vocabulary()
    assert vocab.num_words > 10_000
    assert vocab.branching == 10


def test_skimage_photos_are_available_offline() -> None:
    names = [n for n, _ in skimage_photos()]
    assert len(names) >= 10


def test_default_vocabulary_ranks_revisit_first(shared_data: Path) -> None:
    """slambook2 ch11 desk images: 1.png and 10.png are the same place seen again (the example's
    loop); every other pair is a different viewpoint of the desk."""
    folder = require(shared_data / "images_small" / "slambook2_loop_closure_10")
    vocab = load_default_vocabulary()
    bows = []
    for i in range(1, 11):
        img = cv2.imread(str(folder / f"{i}.png"), cv2.IMREAD_GRAYSCALE)
        bows.append(vocab.transform(detect_orb(img, max_features=1000).descriptors))
    scores = np.array([[l1_score(a, b) for b in bows] for a in bows])
    np.fill_diagonal(scores, -1.0)
    assert np.argmax(scores[0]) == 9  # image 1's best match is image 10
    assert np.argmax(scores[9]) == 0  # and the other way round
    iu = np.triu_indices(10, 1)
    others = np.delete(scores[iu], np.flatnonzero((iu[0] == 0) & (iu[1] == 9)))
    assert scores[0, 9] > others.max()  # the revisit outranks all 44 non-revisit pairs


def test_slam_vocab_cli(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from tools.cli import main as slam_main

    for i, (_, photo) in enumerate(skimage_photos()[:3]):
        cv2.imwrite(str(tmp_path / f"img{i}.png"), photo)
    out = tmp_path / "v.npz"
    assert (
        slam_main(
            [
                "vocab",
                "train",
                str(tmp_path / "*.png"),
                "--k",
                "4",
                "--levels",
                "2",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    assert Vocabulary.load(out).num_words <= 16
    assert slam_main(["vocab", "info", str(out)]) == 0
    assert "words" in capsys.readouterr().out
    assert slam_main(["vocab", "train", "--out", str(tmp_path / "x.npz")]) == 2
