"""Vocabulary tree: Hamming distance, majority centres, TF-IDF, L1 score, descent, file format."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from neb_slam_core.errors import VocabularyError
from neb_slam_core.loop.vocabulary import (
    FORMAT_VERSION,
    BowVector,
    TrainingRecord,
    Vocabulary,
    hamming_distance,
    l1_score,
    majority_centre,
    shipped_vocabulary_path,
    train_vocabulary,
)


def desc(*bytes_) -> np.ndarray:
    """A (32,) descriptor whose first bytes are ``bytes_`` and the rest 0."""
    d = np.zeros(32, np.uint8)
    d[: len(bytes_)] = bytes_
    return d


def test_hamming_distance_of_known_bytes():
    zero = desc()
    assert hamming_distance(zero, zero) == 0
    assert hamming_distance(zero, np.full(32, 0xFF, np.uint8)) == 256
    assert hamming_distance(desc(0b1010_1010), desc(0b0101_0101)) == 8
    assert hamming_distance(desc(0b1000_0001, 0x0F), desc(0b0000_0001, 0xFF)) == 1 + 4
    # broadcasting: (2, 1, 32) against (1, 3, 32) -> (2, 3)
    a = np.stack([zero, desc(0xFF)])[:, None]
    b = np.stack([zero, desc(0x01), desc(0xFF, 0xFF)])[None]
    assert hamming_distance(a, b).tolist() == [[0, 1, 16], [8, 7, 8]]


def test_majority_centre_is_the_bitwise_vote():
    d = np.stack([desc(0b1100, 0xFF), desc(0b1010, 0x0F), desc(0b1001, 0x00)])
    # bit 3 set in all three, bits 2, 1, 0 in one each: 0b1000; byte 1: low nibble in 2 of 3, high in 1 of 3
    assert majority_centre(d)[:2].tolist() == [0b1000, 0x0F]
    # a tie (one of two) gives 0
    assert majority_centre(np.stack([desc(0xFF), desc(0x00)]))[0] == 0
    # it minimises the summed distance: no single-bit flip of it does better
    rng = np.random.default_rng(0)
    members = rng.integers(0, 256, (9, 32), dtype=np.uint8)
    c = majority_centre(members)
    best = hamming_distance(members, c).sum()
    for bit in range(0, 256, 17):
        flipped = c.copy()
        flipped[bit // 8] ^= np.uint8(1 << (7 - bit % 8))
        assert hamming_distance(members, flipped).sum() >= best


def test_l1_score_of_toy_vectors_worked_by_hand():
    a = BowVector(np.array([1, 2]), np.array([0.5, 0.5]))
    b = BowVector(np.array([2, 3]), np.array([0.25, 0.75]))
    # |a - b|_1 = |0.5 - 0| + |0.5 - 0.25| + |0 - 0.75| = 1.5, so s = 1 - 1.5 / 2 = 0.25
    assert l1_score(a, b) == pytest.approx(0.25)
    assert l1_score(a, a) == pytest.approx(1.0)
    assert l1_score(a, BowVector(np.array([7]), np.array([1.0]))) == 0.0
    assert l1_score(a, BowVector.empty()) == 0.0
    dense = 1 - 0.5 * np.abs(a.dense(5) - b.dense(5)).sum()
    assert l1_score(a, b) == pytest.approx(dense)


def four_cluster_corpus() -> tuple[list[np.ndarray], np.ndarray]:
    """Four well-separated descriptor families (bytes 0-7, 8-15, 16-23 or 24-31 set) and images using
    them: family 0 in all 4 images, family 1 in 2, families 2 and 3 in 1 each."""
    rng = np.random.default_rng(1)
    protos = np.zeros((4, 32), np.uint8)
    for f in range(4):
        protos[f, 8 * f : 8 * f + 8] = 0xFF

    def noisy(f: int, n: int) -> np.ndarray:
        d = np.repeat(protos[f][None], n, axis=0)
        flips = rng.integers(0, 256, n)  # one random bit flipped in each copy
        d[np.arange(n), flips // 8] ^= (1 << (flips % 8)).astype(np.uint8)
        return d

    images = [
        np.concatenate([noisy(0, 3), noisy(1, 1)]),
        np.concatenate([noisy(0, 2), noisy(1, 2)]),
        np.concatenate([noisy(0, 1), noisy(2, 3)]),
        np.concatenate([noisy(0, 4), noisy(3, 4)]),
    ]
    return images, protos


def test_tf_idf_of_a_toy_corpus():
    images, protos = four_cluster_corpus()
    vocab = train_vocabulary(images, branching=4, depth=1, seed=0)
    assert vocab.n_words == 4
    word = vocab.words(protos)  # the word of each family
    assert sorted(word.tolist()) == [0, 1, 2, 3]
    # idf = log(N / images containing the word): family 0 in 4 of 4, 1 in 2, 2 and 3 in 1
    assert vocab.idf[word].tolist() == pytest.approx([0.0, math.log(2), math.log(4), math.log(4)])
    # image 1: 2 features of family 0 (weight 0) and 2 of family 1 -> all weight on family 1's word
    v = vocab.transform(images[1])
    assert v.word_ids.tolist() == [word[1]] and v.weights.tolist() == pytest.approx([1.0])
    # families 0 x3, 1 x2, 2 x3: tf-idf 3/8 * 0, 2/8 * log 2, 3/8 * log 4, then L1-normalised
    mixed = np.concatenate([images[1], images[2][1:]])  # families 0 x3, 1 x2, 2 x3
    w1, w2 = 2 / 8 * math.log(2), 3 / 8 * math.log(4)
    v = vocab.transform(mixed)
    expected = {int(word[1]): w1 / (w1 + w2), int(word[2]): w2 / (w1 + w2)}
    assert dict(zip(v.word_ids.tolist(), v.weights.tolist())) == pytest.approx(expected)
    assert v.weights.sum() == pytest.approx(1.0)


def test_descent_matches_a_per_descriptor_reference_and_training_labels():
    rng = np.random.default_rng(3)
    images = [rng.integers(0, 256, (200, 32), dtype=np.uint8) for _ in range(5)]
    vocab = train_vocabulary(images, branching=3, depth=3, seed=1)
    assert vocab.problem() == ""
    assert 9 < vocab.n_words <= 27
    queries = rng.integers(0, 256, (50, 32), dtype=np.uint8)

    def reference_word(d: np.ndarray) -> int:  # the obvious loop, one descriptor at a time
        node = 0
        while vocab.children[node, 0] >= 0:
            kids = [c for c in vocab.children[node] if c >= 0]
            node = kids[int(np.argmin([hamming_distance(d, vocab.centres[c]) for c in kids]))]
        return int(vocab.node_word[node])

    assert vocab.words(queries).tolist() == [reference_word(d) for d in queries]
    # every word is reached by some training descriptor (the tree's leaves hold training clusters)
    assert len(np.unique(vocab.words(np.concatenate(images)))) == vocab.n_words


def test_an_image_matched_to_itself_scores_one_and_differs_from_another():
    images, _ = four_cluster_corpus()
    vocab = train_vocabulary(images, branching=4, depth=1, seed=0)  # one word per family
    vectors = [vocab.transform(i) for i in images]
    assert [l1_score(v, v) for v in vectors] == pytest.approx([1.0] * 4)
    # images 2 and 3 share only family 0, which every image has (idf 0): nothing in common
    assert l1_score(vectors[2], vectors[3]) == 0.0
    # images 0 and 1 differ only in how many family-0 features they have, which weigh nothing
    assert l1_score(vectors[0], vectors[1]) == pytest.approx(1.0)
    assert l1_score(vectors[1], vectors[2]) == 0.0
    assert len(vocab.transform(np.zeros((0, 32), np.uint8))) == 0


def test_training_is_reproducible_for_a_seed():
    rng = np.random.default_rng(5)
    images = [rng.integers(0, 256, (150, 32), dtype=np.uint8) for _ in range(4)]
    a = train_vocabulary(images, branching=4, depth=2, seed=7)
    b = train_vocabulary(images, branching=4, depth=2, seed=7)
    assert np.array_equal(a.centres, b.centres) and np.array_equal(a.idf, b.idf)


def test_file_round_trip(tmp_path):
    images, _ = four_cluster_corpus()
    vocab = train_vocabulary(images, branching=4, depth=2, seed=0, source="toy corpus")
    path = vocab.save(tmp_path / "v.npz")
    assert path == tmp_path / "v.npz" and path.is_file()  # no second ".npz" appended
    back = Vocabulary.load(path)
    for name in ("centres", "children", "node_word", "idf"):
        assert np.array_equal(getattr(back, name), getattr(vocab, name)), name
    assert (back.branching, back.depth) == (4, 2)
    assert back.training == TrainingRecord(4, sum(len(i) for i in images), 0, "toy corpus")
    assert back.transform(images[2]).word_ids.tolist() == vocab.transform(images[2]).word_ids.tolist()


def test_an_old_version_or_a_bad_file_is_an_error_naming_it(tmp_path):
    images, _ = four_cluster_corpus()
    path = train_vocabulary(images, branching=4, depth=1).save(tmp_path / "v.npz")
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["format_version"] = np.array(FORMAT_VERSION + 1)
    old = tmp_path / "old.npz"
    with open(old, "wb") as f:
        np.savez(f, **arrays)
    with pytest.raises(VocabularyError, match=rf"old\.npz.*version {FORMAT_VERSION + 1}.*vocab train"):
        Vocabulary.load(old)
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip")
    with pytest.raises(VocabularyError, match=r"junk\.npz: not a vocabulary file"):
        Vocabulary.load(junk)
    with pytest.raises(VocabularyError, match=r"missing\.npz: no such vocabulary file"):
        Vocabulary.load(tmp_path / "missing.npz")
    arrays["format_version"] = np.array(FORMAT_VERSION)
    arrays["idf"] = arrays["idf"][:-1]
    broken = tmp_path / "broken.npz"
    with open(broken, "wb") as f:
        np.savez(f, **arrays)
    with pytest.raises(VocabularyError, match=r"broken\.npz: inconsistent vocabulary"):
        Vocabulary.load(broken)


def test_the_shipped_vocabulary_loads_fast_and_has_about_ten_thousand_words():
    assert shipped_vocabulary_path().is_file(), "rebuild it with `neb-slam vocab train`"
    t0 = time.perf_counter()
    vocab = Vocabulary.load("")
    assert time.perf_counter() - t0 < 1.0
    assert (vocab.branching, vocab.depth) == (10, 4)
    assert 5000 <= vocab.n_words <= 10**4
    assert vocab.training.n_images > 0 and "vocab train" in vocab.training.source
    assert shipped_vocabulary_path().stat().st_size < 5e6
