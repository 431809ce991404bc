"""A vocabulary tree over binary (ORB) descriptors: visual words, TF-IDF weights, L1 similarity.

The bag-of-words model of DBoW2/DBoW3 (Galvez-Lopez and Tardos, 2012), which the paper uses, written
here with numpy:

- **Tree.** Hierarchical k-majority clustering (k-medians in Hamming space): the training descriptors
  are split into ``branching`` (k) clusters, each cluster again into k, down to ``depth`` (L) levels;
  the leaves are the words (at most k^L: 10^4 for k = 10, L = 4). A cluster's centre is the bitwise
  majority vote of its members, the binary descriptor that minimises the summed Hamming distance to
  them. Seeds are chosen k-means++ style (probability proportional to the squared distance to the
  nearest seed so far). A descriptor's word is found by descending from the root to the nearest child
  at each level: ``k * L`` distances instead of ``k^L``.
- **Weights.** TF-IDF: a word's weight in an image is ``tf * idf`` with ``tf = n_word / n_features``
  (share of the image's features quantised to it) and ``idf = log(N / N_word)``, ``N`` the training
  images and ``N_word`` those that contain the word; a word seen in every training image weighs 0.
- **Vectors.** :class:`BowVector` is sparse (sorted word ids, weights) and L1-normalised.
- **Score.** DBoW's L1 score ``s(a, b) = 1 - |a - b|_1 / 2`` in [0, 1] (1 for the same image). For
  non-negative L1-normalised vectors ``|a_i - b_i| = a_i + b_i - 2 min(a_i, b_i)``, so
  ``s = sum_i min(a_i, b_i)`` over the words the two share: the sparse form used here and by the
  inverted index (:mod:`.database`).

File format (:data:`FORMAT_VERSION`): a ``.npz`` archive (numpy, no pickles) with the fields
``format`` (:data:`FORMAT_NAME`), ``format_version``, ``branching``, ``depth``, ``centres`` ``(n_nodes, 32)``
uint8, ``children`` ``(n_nodes, k)`` int32 (child node ids, -1 where none), ``node_word`` ``(n_nodes,)``
int32 (word id of a leaf, -1 for inner nodes), ``idf`` ``(n_words,)`` float32, and the training
record ``n_training_images``, ``n_training_descriptors``, ``seed``, ``source``. Node 0 is the root (its
centre is unused). The shipped vocabulary (``loop/data/``) is built by ``neb-slam vocab train`` from the
project's synthetic renders.
"""

from __future__ import annotations

import importlib.resources
import logging
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import VocabularyError
from .features import DESCRIPTOR_BYTES

log = logging.getLogger(__name__)

FORMAT_NAME = "neb-slam orb vocabulary"
FORMAT_VERSION = 1
#: the vocabulary that ships with the package (``neb_slam_core/loop/data/``)
SHIPPED_FILE = "orb_vocabulary.npz"

# bits set in each byte value: the popcount fallback for numpy < 2.0 (no np.bitwise_count)
_POPCOUNT_U8 = np.array([bin(i).count("1") for i in range(256)], dtype=np.uint8)
# rows of descriptors compared at once while training (bounds the (rows, k, 4) uint64 temporaries)
_CHUNK_ROWS = 1 << 16


# ------------------------------------------------------------------------------------------ Hamming


def _as_u64(descriptors: np.ndarray) -> np.ndarray:
    """``(..., 32)`` uint8 -> ``(..., 4)`` uint64 (the same bits, 8 bytes at a time)."""
    d = np.ascontiguousarray(descriptors, dtype=np.uint8)
    return d.view(np.uint64)


def _popcount_sum(x: np.ndarray) -> np.ndarray:
    """Set bits of each row of ``x`` ``(..., m)`` (uint8 or uint64) summed over the last axis -> int32."""
    if hasattr(np, "bitwise_count"):
        return np.bitwise_count(x).sum(axis=-1, dtype=np.int32)
    x8 = np.ascontiguousarray(x).view(np.uint8)
    return _POPCOUNT_U8[x8].sum(axis=-1, dtype=np.int32)


def hamming_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamming distance (differing bits) between binary descriptors ``(..., 32)`` uint8, broadcast.

    Example: ``hamming_distance(a, b)`` with ``a`` ``(n, 1, 32)`` and ``b`` ``(1, m, 32)`` gives ``(n, m)``.
    """
    a = np.asarray(a, dtype=np.uint8)
    b = np.asarray(b, dtype=np.uint8)
    if a.shape[-1] != DESCRIPTOR_BYTES or b.shape[-1] != DESCRIPTOR_BYTES:
        raise ValueError(f"binary descriptors must have {DESCRIPTOR_BYTES} bytes, got {a.shape} and {b.shape}")
    return _popcount_sum(np.bitwise_xor(_as_u64(a), _as_u64(b)))


def majority_centre(descriptors: np.ndarray) -> np.ndarray:
    """Bitwise majority vote of ``(n, 32)`` uint8 descriptors -> ``(32,)`` uint8 (a tie gives 0).

    It minimises the summed Hamming distance to the members (each bit independently): the k-medians
    centre in Hamming space.
    """
    bits = np.unpackbits(np.asarray(descriptors, dtype=np.uint8), axis=1)
    return np.packbits(2 * bits.sum(axis=0, dtype=np.int64) > len(bits))


def _nearest(descriptors_u64: np.ndarray, centres_u64: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index and distance of the nearest of ``(m, 4)`` centres for each of ``(n, 4)`` descriptors (ties:
    the lowest index), in chunks of rows."""
    n = len(descriptors_u64)
    label = np.empty(n, dtype=np.int64)
    dist = np.empty(n, dtype=np.int32)
    for s in range(0, n, _CHUNK_ROWS):
        d = _popcount_sum(np.bitwise_xor(descriptors_u64[s : s + _CHUNK_ROWS, None, :], centres_u64[None, :, :]))
        label[s : s + _CHUNK_ROWS] = np.argmin(d, axis=1)
        dist[s : s + _CHUNK_ROWS] = d[np.arange(len(d)), label[s : s + _CHUNK_ROWS]]
    return label, dist


# ------------------------------------------------------------------------------------------ vectors


@dataclass(frozen=True)
class BowVector:
    """A sparse bag-of-words vector.

    Attributes:
        word_ids: ``(n,)`` int32 distinct word ids, increasing.
        weights: ``(n,)`` float32 TF-IDF weights, positive, summing to 1 (empty vector: nothing); float32
            because every keyframe keeps its vector, and scores need no more than 7 digits.
    """

    word_ids: np.ndarray
    weights: np.ndarray

    def __len__(self) -> int:
        return len(self.word_ids)

    @staticmethod
    def empty() -> BowVector:
        return BowVector(np.zeros(0, np.int32), np.zeros(0, np.float32))

    def dense(self, n_words: int) -> np.ndarray:
        """The ``(n_words,)`` dense vector (tests and brute-force checks)."""
        out = np.zeros(n_words)
        out[self.word_ids] = self.weights
        return out


def l1_score(a: BowVector, b: BowVector) -> float:
    """DBoW's L1 similarity ``1 - |a - b|_1 / 2`` of two L1-normalised vectors, in [0, 1].

    Computed over the shared words only, as ``sum min(a_i, b_i)`` (see the module docstring); 0 when
    either vector is empty.
    """
    _, ia, ib = np.intersect1d(a.word_ids, b.word_ids, assume_unique=True, return_indices=True)
    return float(np.minimum(a.weights[ia], b.weights[ib]).sum(dtype=np.float64))


# ---------------------------------------------------------------------------------------- vocabulary


@dataclass(frozen=True)
class TrainingRecord:
    """How a vocabulary was built (stored in its file, for the record)."""

    n_images: int = 0
    n_descriptors: int = 0
    seed: int = 0
    source: str = ""


@dataclass(frozen=True, eq=False)
class Vocabulary:
    """A trained vocabulary tree (see the module docstring for the fields' meaning).

    Attributes:
        branching: k, children per inner node at most.
        depth: L, levels below the root at most.
        centres: ``(n_nodes, 32)`` uint8 node centres; row 0 (the root) is unused.
        children: ``(n_nodes, k)`` int32 child node ids, -1 padded; a leaf has none.
        node_word: ``(n_nodes,)`` int32 word id of each leaf, -1 for inner nodes.
        idf: ``(n_words,)`` float32 inverse document frequency of each word.
        training: the training record.
    """

    branching: int
    depth: int
    centres: np.ndarray
    children: np.ndarray
    node_word: np.ndarray
    idf: np.ndarray
    training: TrainingRecord = field(default_factory=TrainingRecord)

    @property
    def n_words(self) -> int:
        return len(self.idf)

    @property
    def n_nodes(self) -> int:
        return len(self.centres)

    def words(self, descriptors: np.ndarray) -> np.ndarray:
        """Word id ``(N,)`` int32 of each of ``(N, 32)`` uint8 descriptors.

        All descriptors descend together, one tree level per step: at each level the ``(n, k)``
        distances to the children of each descriptor's current node, then the nearest child (the lowest
        index on ties, as in training). A descriptor whose node is a leaf stays there.
        """
        d = _as_u64(np.asarray(descriptors, dtype=np.uint8).reshape(-1, DESCRIPTOR_BYTES))
        node = np.zeros(len(d), dtype=np.int64)
        centres = _as_u64(self.centres)
        for _ in range(self.depth):
            kids = self.children[node]  # (N, k), -1 padded
            active = np.flatnonzero(kids[:, 0] >= 0)  # children are packed first, so col 0 tells
            if active.size == 0:
                break
            kids = kids[active]
            dist = _popcount_sum(np.bitwise_xor(d[active, None, :], centres[np.maximum(kids, 0)]))
            dist[kids < 0] = np.iinfo(np.int32).max
            node[active] = kids[np.arange(len(active)), np.argmin(dist, axis=1)]
        return self.node_word[node]

    def transform(self, descriptors: np.ndarray) -> BowVector:
        """The L1-normalised TF-IDF :class:`BowVector` of one image's ``(N, 32)`` descriptors.

        Words whose weight is 0 (idf 0: seen in every training image) are left out, so that they cost
        nothing in the inverted index; an image with no weighted word gives the empty vector.
        """
        descriptors = np.asarray(descriptors, dtype=np.uint8).reshape(-1, DESCRIPTOR_BYTES)
        if len(descriptors) == 0:
            return BowVector.empty()
        ids, counts = np.unique(self.words(descriptors), return_counts=True)
        w = counts / len(descriptors) * self.idf[ids].astype(np.float64)
        keep = w > 0
        ids, w = ids[keep], w[keep]
        total = w.sum()
        if total <= 0:
            return BowVector.empty()
        return BowVector(ids.astype(np.int32), (w / total).astype(np.float32))

    # ---------------------------------------------------------------------------------- file I/O

    def save(self, path: str | Path) -> Path:
        """Write the vocabulary to ``path`` (a ``.npz`` archive, see the module docstring); returns it."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "wb") as f:  # a file object, so numpy does not append its own ".npz"
            np.savez_compressed(
                f,
                format=np.array(FORMAT_NAME),
                format_version=np.array(FORMAT_VERSION, np.int32),
                branching=np.array(self.branching, np.int32),
                depth=np.array(self.depth, np.int32),
                centres=self.centres.astype(np.uint8),
                children=self.children.astype(np.int32),
                node_word=self.node_word.astype(np.int32),
                idf=self.idf.astype(np.float32),
                n_training_images=np.array(self.training.n_images, np.int64),
                n_training_descriptors=np.array(self.training.n_descriptors, np.int64),
                seed=np.array(self.training.seed, np.int64),
                source=np.array(self.training.source),
            )
        return path

    @staticmethod
    def load(path: str | Path = "") -> Vocabulary:
        """Read a vocabulary file; ``""`` reads the shipped one (:func:`shipped_vocabulary_path`).

        Raises:
            VocabularyError: the file is missing, not a vocabulary, of another format version, or its
                arrays are inconsistent; the message names the file.
        """
        path = Path(path) if str(path) else shipped_vocabulary_path()
        if not path.is_file():
            raise VocabularyError(
                path,
                "no such vocabulary file"
                + (
                    " (the shipped vocabulary is missing: rebuild it with `neb-slam vocab train`)"
                    if path == shipped_vocabulary_path()
                    else ""
                ),
            )
        try:
            with np.load(path, allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files}
        except Exception as exc:
            raise VocabularyError(path, f"not a vocabulary file (.npz expected): {exc}") from None
        if "format_version" not in arrays or str(arrays.get("format", "")) != FORMAT_NAME:
            raise VocabularyError(path, f"not a {FORMAT_NAME!r} file (no format/format_version fields)")
        version = int(arrays["format_version"])
        if version != FORMAT_VERSION:
            raise VocabularyError(
                path,
                f"vocabulary format version {version}, this version of neb_slam_core "
                f"reads version {FORMAT_VERSION}; retrain it with `neb-slam vocab train`",
            )
        missing = [k for k in ("branching", "depth", "centres", "children", "node_word", "idf") if k not in arrays]
        if missing:
            raise VocabularyError(path, f"vocabulary file lacks the fields {', '.join(missing)}")
        vocab = Vocabulary(
            branching=int(arrays["branching"]),
            depth=int(arrays["depth"]),
            centres=np.ascontiguousarray(arrays["centres"], np.uint8),
            children=arrays["children"].astype(np.int32),
            node_word=arrays["node_word"].astype(np.int32),
            idf=arrays["idf"].astype(np.float32),
            training=TrainingRecord(
                int(arrays.get("n_training_images", 0)),
                int(arrays.get("n_training_descriptors", 0)),
                int(arrays.get("seed", 0)),
                str(arrays.get("source", "")),
            ),
        )
        problem = vocab.problem()
        if problem:
            raise VocabularyError(path, f"inconsistent vocabulary: {problem}")
        return vocab

    def problem(self) -> str:
        """What is inconsistent in the arrays ('' when nothing)."""
        n, k = self.n_nodes, self.branching
        if k < 2 or self.depth < 1:
            return f"branching {k} and depth {self.depth} (expected >= 2 and >= 1)"
        if self.centres.shape != (n, DESCRIPTOR_BYTES) or n < 2:
            return f"centres have shape {self.centres.shape}, expected (n_nodes >= 2, {DESCRIPTOR_BYTES})"
        if self.children.shape != (n, k) or self.node_word.shape != (n,):
            return f"children {self.children.shape} / node_word {self.node_word.shape} do not match {n} nodes, k={k}"
        if self.children.min() < -1 or self.children.max() >= n:
            return "child ids out of range"
        leaves = self.children[:, 0] < 0
        if np.any(self.node_word[~leaves] != -1) or not np.array_equal(
            np.sort(self.node_word[leaves]), np.arange(leaves.sum())
        ):
            return "leaves must hold the word ids 0..n_words-1 and inner nodes -1"
        if len(self.idf) != leaves.sum() or not np.all(np.isfinite(self.idf)) or self.idf.min() < 0:
            return f"idf has {len(self.idf)} entries for {int(leaves.sum())} words, or is negative / not finite"
        return ""


def shipped_vocabulary_path() -> Path:
    """Path of the vocabulary shipped in the package (``neb_slam_core/loop/data/orb_vocabulary.npz``)."""
    return Path(str(importlib.resources.files("neb_slam_core.loop").joinpath("data", SHIPPED_FILE)))


def load_vocabulary(path: str | Path = "") -> Vocabulary:
    """:meth:`Vocabulary.load` (``""``: the shipped vocabulary)."""
    return Vocabulary.load(path)


# ------------------------------------------------------------------------------------------ training


def _seed_centres(d: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """Up to ``k`` seed rows of ``(n, 4)`` uint64 descriptors, k-means++: each next seed drawn with
    probability proportional to the squared distance to the nearest seed so far (stops early when
    every descriptor equals a seed)."""
    chosen = [int(rng.integers(len(d)))]
    nearest = _popcount_sum(np.bitwise_xor(d, d[chosen[0]])).astype(np.float64)
    while len(chosen) < k:
        p = nearest * nearest
        total = p.sum()
        if total <= 0:
            break
        i = int(rng.choice(len(d), p=p / total))
        chosen.append(i)
        nearest = np.minimum(nearest, _popcount_sum(np.bitwise_xor(d, d[i])))
    return d[chosen].copy()


def _k_majority(
    d_u8: np.ndarray, k: int, rng: np.random.Generator, max_iterations: int
) -> tuple[np.ndarray, np.ndarray]:
    """Cluster ``(n, 32)`` uint8 descriptors into at most ``k`` groups by k-majority.

    Returns:
        centres ``(m, 32)`` uint8 (m <= k, no empty cluster) and the label ``(n,)`` of each descriptor,
        which is its nearest centre (lowest index on ties) so that descending the tree reproduces it.
    """
    d = _as_u64(d_u8)
    centres = _seed_centres(d, k, rng)
    bits = np.unpackbits(d_u8, axis=1)  # (n, 256), once per node
    labels = None
    for _ in range(max_iterations):
        new_labels, _ = _nearest(d, centres)
        if labels is not None and np.array_equal(new_labels, labels):
            break
        labels = new_labels
        # majority vote per cluster: members grouped by label, ones per bit summed per group
        order = np.argsort(labels, kind="stable")
        _, starts, sizes = np.unique(labels[order], return_index=True, return_counts=True)
        counts = np.add.reduceat(bits[order], starts, axis=0, dtype=np.int32)  # (m, 256)
        centres = _as_u64(np.packbits(2 * counts > sizes[:, None], axis=1))  # empty clusters drop out here
    labels, _ = _nearest(d, centres)
    used = np.unique(labels)
    if len(used) < len(centres):  # a centre that lost all members in the final assignment
        centres = centres[used]
        labels, _ = _nearest(d, centres)
    return np.ascontiguousarray(centres).view(np.uint8).reshape(-1, DESCRIPTOR_BYTES), labels


def train_vocabulary(
    descriptors_per_image: Sequence[np.ndarray],
    branching: int = 10,
    depth: int = 4,
    seed: int = 0,
    max_iterations: int = 10,
    source: str = "",
    progress: Callable[[int, int], None] | None = None,
) -> Vocabulary:
    """Build a vocabulary tree and its idf weights from training images' descriptors.

    Args:
        descriptors_per_image: one ``(N_i, 32)`` uint8 array per training image.
        branching: k, clusters per node.
        depth: L, levels; at most k^L words.
        seed: drives the k-means++ seeding (the result is a function of the inputs and the seed).
        max_iterations: k-majority iterations per node at most (it stops earlier when stable).
        source: a note on the training data, kept in the file.
        progress: called as ``progress(nodes_done, nodes_queued_so_far)`` while clustering.
    """
    if branching < 2 or depth < 1:
        raise ValueError(f"train_vocabulary: branching must be >= 2 and depth >= 1, got {branching}, {depth}")
    per_image = [np.asarray(x, dtype=np.uint8).reshape(-1, DESCRIPTOR_BYTES) for x in descriptors_per_image]
    all_d = np.ascontiguousarray(np.concatenate(per_image, axis=0)) if per_image else np.zeros((0, 32), np.uint8)
    if len(all_d) < branching:
        raise ValueError(f"train_vocabulary: {len(all_d)} descriptors are too few for branching {branching}")
    rng = np.random.default_rng(seed)

    centres: list[np.ndarray] = [np.zeros(DESCRIPTOR_BYTES, np.uint8)]
    children: list[list[int]] = [[]]
    queue: deque[tuple[int, np.ndarray, int]] = deque([(0, np.arange(len(all_d)), 0)])
    done = 0
    while queue:  # breadth first, so word ids run level by level, left to right
        node, members, level = queue.popleft()
        done += 1
        if progress is not None:
            progress(done, len(centres))
        if level == depth:
            continue
        d = all_d[members]
        uniq, inverse = np.unique(d, axis=0, return_inverse=True)
        if len(uniq) <= 1:
            continue  # identical descriptors: nothing to split, the node is a leaf
        if len(uniq) <= branching:
            c, labels = uniq, inverse.reshape(-1)  # every distinct descriptor is its own cluster
        else:
            c, labels = _k_majority(d, branching, rng, max_iterations)
        for j in range(len(c)):
            child = len(centres)
            centres.append(c[j])
            children.append([])
            children[node].append(child)
            queue.append((child, members[labels == j], level + 1))

    n_nodes = len(centres)
    child_arr = np.full((n_nodes, branching), -1, dtype=np.int32)
    for i, kids in enumerate(children):
        child_arr[i, : len(kids)] = kids
    node_word = np.full(n_nodes, -1, dtype=np.int32)
    leaves = np.flatnonzero(child_arr[:, 0] < 0)
    node_word[leaves] = np.arange(len(leaves), dtype=np.int32)
    vocab = Vocabulary(
        branching, depth, np.stack(centres).astype(np.uint8), child_arr, node_word, np.zeros(len(leaves), np.float32)
    )

    # idf = log(N / N_word) over the training images; a word no training image reaches when descending
    # (possible only through ties) counts as seen once
    n_images = len(per_image)
    containing = np.zeros(len(leaves), dtype=np.int64)
    for d in per_image:
        if len(d):
            containing[np.unique(vocab.words(d))] += 1
    idf = np.log(n_images / np.maximum(containing, 1)).astype(np.float32)
    return Vocabulary(
        branching,
        depth,
        vocab.centres,
        child_arr,
        node_word,
        idf,
        TrainingRecord(n_images, int(len(all_d)), int(seed), source),
    )
