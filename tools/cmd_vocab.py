"""`slam vocab`: train and inspect ORB bag-of-words vocabularies."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

DESCRIPTION = """\
Bag-of-words vocabularies for place recognition (loop closure, relocalisation): a tree of
binary ORB words built by hierarchical k-medians (Hamming distance), with TF-IDF weights.

  train   cluster the ORB descriptors of images or sequences into a vocabulary (.npz)
  info    print a vocabulary's size and shape

The package ships a default vocabulary (slam/loop/default_vocab.npz) trained with
`slam vocab train --default` on scikit-image's sample photographs plus random variants;
train your own on images like the ones you will run on for better place recognition.

Examples:
  slam vocab train --default --out slam/loop/default_vocab.npz
  slam vocab train 'photos/*.jpg' indoor_pics/ --out indoor.npz --levels 5
  slam vocab train room1.mcap room2.mcap --every-nth 5 --out rooms.npz
  slam vocab info indoor.npz
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "vocab",
        help="train or inspect ORB bag-of-words vocabularies",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = p.add_subparsers(dest="vocab_command", metavar="ACTION", required=True)

    t = sub.add_parser(
        "train",
        help="train a vocabulary from images and/or sequences",
        description=(
            "Train a vocabulary tree on ORB descriptors.\n\nInputs: image files, globs (quote "
            "them), folders of images (recursive), or sequences (MCAP files, EuRoC/TUM-VI "
            "folders: every Nth left frame).\n\nExample:\n"
            "  slam vocab train 'imgs/*.png' seq.mcap --out my_vocab.npz --k 10 --levels 5"
        ),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    t.add_argument("inputs", nargs="*", help="images, globs, image folders or sequences")
    t.add_argument("--out", type=Path, required=True, help="output vocabulary (.npz)")
    t.add_argument(
        "--default",
        action="store_true",
        help="also train on the default set (augmented scikit-image sample photographs)",
    )
    t.add_argument("--k", type=int, default=10, help="branching factor (default 10)")
    t.add_argument("--levels", type=int, default=5, help="tree depth L (default 5)")
    t.add_argument(
        "--max-features", type=int, default=1000, help="ORB features per image (default 1000)"
    )
    t.add_argument(
        "--every-nth", type=int, default=10, help="sequences: use every Nth frame (default 10)"
    )
    t.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    t.set_defaults(func=run_train)

    i = sub.add_parser(
        "info",
        help="describe a vocabulary file",
        description="Print the size and shape of a vocabulary.\n\nExample:\n  slam vocab info v.npz",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    i.add_argument("file", type=Path, help="vocabulary (.npz); 'default' for the shipped one")
    i.set_defaults(func=run_info)


def run_train(args: argparse.Namespace) -> int:
    from slam.loop.training import VocabTrainOptions, train_vocabulary

    t0 = time.perf_counter()
    vocab, n_images, n_desc = train_vocabulary(
        args.inputs,
        VocabTrainOptions(
            branching=args.k,
            levels=args.levels,
            max_features=args.max_features,
            every_nth=args.every_nth,
            seed=args.seed,
        ),
        default_set=args.default,
    )
    vocab.save(args.out)
    print(
        f"trained on {n_images} images, {n_desc} descriptors: {vocab.num_words} words, "
        f"{vocab.num_nodes} nodes (k={vocab.branching}, L={vocab.levels}) "
        f"in {time.perf_counter() - t0:.1f} s"
    )
    print(f"wrote {args.out} ({args.out.stat().st_size / 1e6:.2f} MB)")
    return 0


def run_info(args: argparse.Namespace) -> int:
    from slam.loop.vocabulary import Vocabulary, default_vocabulary_path, timed_load

    path = default_vocabulary_path() if str(args.file) == "default" else args.file
    vocab, seconds = timed_load(path)
    print(f"{path}: {path.stat().st_size / 1e6:.2f} MB, loaded in {seconds * 1e3:.0f} ms")
    for key, value in vocab.describe().items():
        print(f"  {key:16s} {value:.4g}" if isinstance(value, float) else f"  {key:16s} {value}")
    assert isinstance(vocab, Vocabulary)
    return 0
