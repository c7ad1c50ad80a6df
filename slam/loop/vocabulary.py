"""A vocabulary tree over 256-bit ORB descriptors (bag of binary words, DBoW2-style).

Written here because no usable bag-of-words library for binary descriptors installs on
Python 3.11 (pydbow3/dbow3py do not build; pydbow is pure Python at ~90 ms per image), and no
PyPI package ships an ORB vocabulary (see ../shared/design/FIELD_NOTES.md).

* Training: hierarchical k-medians. Each node's descriptors are split into ``k`` clusters with
  k-means++ seeding under the Hamming distance, assignments by Hamming distance and centres by a
  bitwise majority vote; recursion stops at ``levels`` or when a node has ``<= k`` descriptors
  (each then becomes its own child). Leaves are the words.
* Weights: TF-IDF. ``idf(w) = log(N_images / n_images_containing_w)``; a BoW vector holds
  ``tf * idf`` per word, L1-normalised.
* Score: the L1 score of DBoW2, ``s(v, w) = 1 - |v - w|_1 / 2 = sum_i min(v_i, w_i)`` for
  L1-normalised non-negative vectors (1 = identical, 0 = no common word).
* Transform: descriptors descend the tree one level at a time, all at once (numpy
  ``bitwise_count`` on uint64 words).
* Storage: ``.npz`` (compressed) with the node descriptors (uint8), each node's parent and the
  word weights; nodes are stored breadth first so every node's children are contiguous.
"""

from __future__ import annotations

import io
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from slam.core.atomic import write_atomic
from slam.core.errors import InputError

DESCRIPTOR_BYTES = 32  # ORB: 256 bits
FORMAT_VERSION = 1
DEFAULT_VOCABULARY_FILE = "default_vocab.npz"


@dataclass(frozen=True, eq=False)
class BowVector:
    """A sparse bag-of-words vector: sorted unique ``word_ids`` (int32) and their L1-normalised
    TF-IDF ``weights`` (float32, sum 1 unless empty)."""

    word_ids: np.ndarray
    weights: np.ndarray

    def __len__(self) -> int:
        return len(self.word_ids)


def l1_score(a: BowVector, b: BowVector) -> float:
    """DBoW2's L1 score ``1 - |a - b|_1 / 2`` in [0, 1] (= sum of min weights of common words)."""
    _, ia, ib = np.intersect1d(a.word_ids, b.word_ids, assume_unique=True, return_indices=True)
    return float(np.minimum(a.weights[ia], b.weights[ib]).sum())


def hamming_to_centres(desc64: np.ndarray, centres64: np.ndarray) -> np.ndarray:
    """(N, K) uint16 Hamming distances between (N, 4) and (K, 4) uint64 descriptors."""
    out = np.zeros((len(desc64), len(centres64)), dtype=np.uint16)
    for j in range(desc64.shape[1]):
        out += np.bitwise_count(desc64[:, j, None] ^ centres64[None, :, j])
    return out


def _as64(descriptors: np.ndarray) -> np.ndarray:
    d = np.ascontiguousarray(descriptors, dtype=np.uint8)
    if d.ndim != 2 or d.shape[1] != DESCRIPTOR_BYTES:
        raise ValueError(f"expected (N, {DESCRIPTOR_BYTES}) uint8 descriptors, got {d.shape}")
    return d.view(np.uint64)


def _majority(desc: np.ndarray) -> np.ndarray:
    """Bitwise majority vote of (n, 32) uint8 descriptors (ties -> 0), as (32,) uint8."""
    counts = np.zeros(8 * DESCRIPTOR_BYTES, dtype=np.int64)
    for start in range(0, len(desc), 65536):  # bounded memory for the root's big clusters
        counts += np.unpackbits(desc[start : start + 65536], axis=1).sum(axis=0, dtype=np.int64)
    return np.packbits(2 * counts > len(desc))


def _kmedians(
    desc: np.ndarray, k: int, rng: np.random.Generator, max_iterations: int
) -> tuple[np.ndarray, np.ndarray]:
    """Split (n, 32) uint8 descriptors (n > k) into k clusters: (centres (k, 32), labels (n,))."""
    d64 = desc.view(np.uint64)
    n = len(desc)
    # k-means++ seeding: next centre drawn with probability ~ squared distance to the nearest.
    centres = [int(rng.integers(n))]
    nearest = hamming_to_centres(d64, d64[centres[0] : centres[0] + 1])[:, 0].astype(np.float64)
    for _ in range(1, k):
        p = nearest**2
        total = p.sum()
        if total <= 0:  # all remaining descriptors coincide with a centre
            break
        c = int(rng.choice(n, p=p / total))
        centres.append(c)
        np.minimum(nearest, hamming_to_centres(d64, d64[c : c + 1])[:, 0], out=nearest)
    centre_desc = desc[centres].copy()
    labels = np.full(n, -1, dtype=np.int64)
    for _ in range(max_iterations):
        new_labels = np.argmin(hamming_to_centres(d64, centre_desc.view(np.uint64)), axis=1)
        if np.array_equal(new_labels, labels):
            break
        labels = new_labels
        order = np.argsort(labels, kind="stable")
        bounds = np.searchsorted(labels[order], np.arange(len(centre_desc) + 1))
        for c in range(len(centre_desc)):
            members = order[bounds[c] : bounds[c + 1]]
            if len(members):
                centre_desc[c] = _majority(desc[members])
    # Drop empty clusters (possible with duplicated descriptors).
    used = np.unique(labels)
    remap = np.full(len(centre_desc), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return centre_desc[used], remap[labels]


class Vocabulary:
    """A trained vocabulary tree. Build with :meth:`train` or :meth:`load`.

    Arrays (nodes breadth first, node 0 = root): ``node_descriptors`` (M, 32) uint8,
    ``parents`` (M,) int32 (-1 for the root), ``node_words`` (M,) int32 (word id of a leaf,
    -1 otherwise), ``idf`` (W,) float32.
    """

    def __init__(
        self,
        node_descriptors: np.ndarray,
        parents: np.ndarray,
        idf: np.ndarray,
        branching: int,
        levels: int,
    ) -> None:
        self.node_descriptors = np.ascontiguousarray(node_descriptors, dtype=np.uint8)
        self.parents = np.asarray(parents, dtype=np.int32)
        self.idf = np.asarray(idf, dtype=np.float32)
        self.branching = int(branching)
        self.levels = int(levels)
        m = len(self.parents)
        if self.node_descriptors.shape != (m, DESCRIPTOR_BYTES) or m < 2:
            raise InputError("vocabulary arrays disagree (node descriptors vs parents)")
        child_parents = self.parents[1:]
        if np.any(np.diff(child_parents) < 0) or np.any(child_parents >= np.arange(1, m)):
            raise InputError("vocabulary nodes are not stored breadth first")
        # Children of node p are the contiguous block [first_child[p], first_child[p] + n[p]).
        num_children = np.bincount(child_parents, minlength=m).astype(np.int32)
        first_child = np.searchsorted(child_parents, np.arange(m)).astype(np.int32) + 1
        self.children = np.where(
            np.arange(self.branching)[None, :] < num_children[:, None],
            first_child[:, None] + np.arange(self.branching)[None, :],
            -1,
        ).astype(np.int32)
        leaves = num_children == 0
        self.node_words = np.full(m, -1, dtype=np.int32)
        self.node_words[leaves] = np.arange(int(leaves.sum()), dtype=np.int32)
        if len(self.idf) != int(leaves.sum()):
            raise InputError(
                f"vocabulary has {int(leaves.sum())} leaves but {len(self.idf)} word weights"
            )
        self._node64 = self.node_descriptors.view(np.uint64)
        self.node_depths = self._node_depths()
        self._depth = int(self.node_depths.max())

    # ---------------------------------------------------------------------------- properties
    @property
    def num_words(self) -> int:
        return len(self.idf)

    @property
    def num_nodes(self) -> int:
        return len(self.parents)

    def _node_depths(self) -> np.ndarray:
        """(M,) depth of each node (root 0), by repeated vectorised propagation."""
        depth = np.zeros(self.num_nodes, dtype=np.int32)
        for _ in range(self.num_nodes):
            new = depth.copy()
            new[1:] = depth[self.parents[1:]] + 1
            if np.array_equal(new, depth):
                break
            depth = new
        return depth

    # ---------------------------------------------------------------------------- transform
    def words(self, descriptors: np.ndarray) -> np.ndarray:
        """Word id (int32) of each of (N, 32) uint8 descriptors."""
        d64 = _as64(descriptors)
        node = np.zeros(len(d64), dtype=np.int64)
        rows = np.arange(len(d64))
        for _ in range(self._depth):
            kids = self.children[node]  # (N, k), -1 where missing
            active = kids[:, 0] >= 0
            if not active.any():
                break
            dist = np.zeros(kids.shape, dtype=np.uint16)
            cand = self._node64[np.maximum(kids, 0)]  # (N, k, 4)
            for j in range(d64.shape[1]):
                dist += np.bitwise_count(cand[:, :, j] ^ d64[:, j, None])
            dist[kids < 0] = np.iinfo(np.uint16).max
            best = kids[rows, np.argmin(dist, axis=1)]
            node = np.where(active, best, node)
        return self.node_words[node]

    def transform(self, descriptors: np.ndarray) -> BowVector:
        """L1-normalised TF-IDF bag-of-words vector of one image's descriptors."""
        if len(descriptors) == 0:
            return BowVector(np.zeros(0, np.int32), np.zeros(0, np.float32))
        ids, counts = np.unique(self.words(descriptors), return_counts=True)
        weights = counts.astype(np.float32) / float(len(descriptors)) * self.idf[ids]
        total = float(weights.sum())
        keep = weights > 0
        ids, weights = ids[keep], weights[keep]
        if total > 0:
            weights = weights / np.float32(total)
        return BowVector(ids.astype(np.int32), weights.astype(np.float32))

    def score(self, a: BowVector, b: BowVector) -> float:
        """L1 score in [0, 1] (see :func:`l1_score`)."""
        return l1_score(a, b)

    # ---------------------------------------------------------------------------- training
    @staticmethod
    def train(
        descriptors_per_image: Sequence[np.ndarray],
        branching: int = 10,
        levels: int = 5,
        seed: int = 0,
        max_iterations: int = 10,
        progress: Callable[[int], None] | None = None,
    ) -> Vocabulary:
        """Train on the ORB descriptors of a set of images (one (n_i, 32) uint8 array each).

        The per-image grouping is only used for the IDF weights. ``progress`` (optional) is
        called with increments of (descriptors x levels) done; the total is N x levels.
        """
        if branching < 2 or levels < 1:
            raise InputError("vocabulary needs branching >= 2 and levels >= 1")
        arrays = [np.ascontiguousarray(d, dtype=np.uint8) for d in descriptors_per_image]
        arrays = [a for a in arrays if len(a)]
        if not arrays:
            raise InputError("no descriptors to train a vocabulary on")
        for a in arrays:
            _as64(a)
        all_desc = np.concatenate(arrays)
        image_of = np.repeat(np.arange(len(arrays)), [len(a) for a in arrays])
        rng = np.random.default_rng(seed)

        node_desc: list[np.ndarray] = [np.zeros(DESCRIPTOR_BYTES, np.uint8)]
        parents: list[int] = [-1]
        leaf_members: dict[int, np.ndarray] = {}
        # Breadth-first: a queue of (node id, member indices, depth).
        queue: deque[tuple[int, np.ndarray, int]] = deque([(0, np.arange(len(all_desc)), 0)])
        while queue:
            node, members, depth = queue.popleft()
            if depth == levels or len(members) <= 1:
                leaf_members[node] = members
                if progress:
                    progress(len(members) * (levels - depth))
                continue
            if progress:
                progress(len(members))
            desc = all_desc[members]
            if len(members) <= branching:
                centres, labels = desc, np.arange(len(members))
            else:
                centres, labels = _kmedians(desc, branching, rng, max_iterations)
            if len(centres) == 1:  # every member identical: this node is a leaf
                leaf_members[node] = members
                if progress:
                    progress(len(members) * (levels - depth - 1))
                continue
            for c in range(len(centres)):
                child = len(parents)
                parents.append(node)
                node_desc.append(centres[c])
                queue.append((child, members[labels == c], depth + 1))

        parents_arr = np.array(parents, dtype=np.int32)
        is_leaf = np.bincount(parents_arr[1:], minlength=len(parents_arr)) == 0
        leaf_nodes = np.flatnonzero(is_leaf)
        # IDF from the number of training images that contain each word.
        n_images = len(arrays)
        idf = np.zeros(len(leaf_nodes), dtype=np.float64)
        for w, leaf in enumerate(leaf_nodes.tolist()):
            n_with = len(np.unique(image_of[leaf_members[leaf]]))
            idf[w] = np.log(n_images / max(n_with, 1))
        return Vocabulary(
            np.array(node_desc), parents_arr, idf.astype(np.float32), branching, levels
        )

    # ---------------------------------------------------------------------------- storage
    def save(self, path: str | Path) -> None:
        """Write a compressed ``.npz`` (atomically)."""
        path = Path(path)
        buf = io.BytesIO()
        np.savez_compressed(
            buf,
            format_version=np.int32(FORMAT_VERSION),
            branching=np.int32(self.branching),
            levels=np.int32(self.levels),
            node_descriptors=self.node_descriptors,
            parents=self.parents,
            idf=self.idf,
        )
        write_atomic(path, buf.getvalue())

    @staticmethod
    def load(path: str | Path) -> Vocabulary:
        """Read a vocabulary written by :meth:`save`."""
        path = Path(path)
        if not path.is_file():
            raise InputError(f"{path}: no such vocabulary file")
        try:
            with np.load(path, allow_pickle=False) as z:
                version = int(z["format_version"])
                if version != FORMAT_VERSION:
                    raise InputError(
                        f"{path}: vocabulary format {version}, this version reads "
                        f"{FORMAT_VERSION}; retrain with `slam vocab train`"
                    )
                return Vocabulary(
                    z["node_descriptors"],
                    z["parents"],
                    z["idf"],
                    int(z["branching"]),
                    int(z["levels"]),
                )
        except (KeyError, ValueError, OSError) as exc:
            raise InputError(f"{path}: not a vocabulary file ({exc})") from exc

    def describe(self) -> dict[str, float | int]:
        """Summary numbers (for `slam vocab info`)."""
        leaf_depths = self.node_depths[self.node_words >= 0]
        return {
            "branching": self.branching,
            "levels": self.levels,
            "nodes": self.num_nodes,
            "words": self.num_words,
            "mean_leaf_depth": float(leaf_depths.mean()),
            "idf_min": float(self.idf.min()),
            "idf_max": float(self.idf.max()),
        }


def default_vocabulary_path() -> Path:
    """Where the shipped default vocabulary lives (inside the installed package)."""
    return Path(str(resources.files("slam.loop").joinpath(DEFAULT_VOCABULARY_FILE)))


def load_default_vocabulary() -> Vocabulary:
    """The vocabulary shipped with the package (trained on scikit-image's sample photographs,
    see ``tools/cmd_vocab.py``)."""
    path = default_vocabulary_path()
    if not path.is_file():
        raise InputError(
            f"default vocabulary missing at {path}; run `slam vocab train --default --out {path}`"
        )
    return Vocabulary.load(path)


def timed_load(path: str | Path) -> tuple[Vocabulary, float]:
    """Load a vocabulary and return it with the wall time it took (s)."""
    t0 = time.perf_counter()
    vocab = Vocabulary.load(path)
    return vocab, time.perf_counter() - t0
