"""Training material for vocabularies: image files, sequences, and the default photo set.

The default vocabulary is trained on scikit-image's bundled sample photographs (shipped with
the scikit-image wheel, no download), augmented by random crops, scales, rotations, blur and
brightness/contrast changes so that there are 100k+ varied ORB descriptors. Never on the
project's shared test data.
"""

from __future__ import annotations

import glob
import logging
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from slam.core.errors import InputError
from slam.loop.orb import detect_orb
from slam.loop.vocabulary import Vocabulary

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".pgm", ".ppm", ".bmp", ".tif", ".tiff")

# Natural photographs bundled in the scikit-image wheel (the others need a download or are
# synthetic/binary and give few useful corners).
SKIMAGE_PHOTOS = (
    "astronaut",
    "brick",
    "camera",
    "cell",
    "chelsea",
    "clock",
    "coffee",
    "coins",
    "grass",
    "gravel",
    "hubble_deep_field",
    "immunohistochemistry",
    "moon",
    "page",
    "retina",
    "rocket",
    "text",
    "stereo_motorcycle",
)


@dataclass(frozen=True)
class AugmentOptions:
    """How many random variants of each photo, and how strong."""

    variants_per_image: int = 16
    min_scale: float = 0.6
    max_scale: float = 1.6
    max_rotation_deg: float = 30.0
    max_blur_sigma_px: float = 1.5
    seed: int = 0


def _to_gray_u8(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim == 3:
        img = img[..., :3]
        img = cv2.cvtColor(np.ascontiguousarray(img.astype(np.uint8)), cv2.COLOR_RGB2GRAY)
    if img.dtype != np.uint8:
        lo, hi = float(img.min()), float(img.max())
        img = ((img - lo) / max(hi - lo, 1e-12) * 255.0).astype(np.uint8)
    return img


def skimage_photos() -> list[tuple[str, np.ndarray]]:
    """(name, grey uint8 image) of the scikit-image sample photographs available offline."""
    import skimage.data

    out = []
    for name in SKIMAGE_PHOTOS:
        try:
            img = getattr(skimage.data, name)()
        except Exception as exc:  # a photo that needs a download (pooch) or failed to load
            log.debug("skimage.data.%s unavailable: %s", name, exc)
            continue
        if name == "stereo_motorcycle":
            out.append((name + "_left", _to_gray_u8(img[0])))
            out.append((name + "_right", _to_gray_u8(img[1])))
        else:
            out.append((name, _to_gray_u8(img)))
    if not out:
        raise InputError("no scikit-image sample photographs could be loaded")
    return out


def augment(image: np.ndarray, rng: np.random.Generator, opts: AugmentOptions) -> np.ndarray:
    """One random variant: scale + rotation about a random centre, crop, blur, gain/offset."""
    h, w = image.shape
    scale = float(np.exp(rng.uniform(np.log(opts.min_scale), np.log(opts.max_scale))))
    angle = float(rng.uniform(-opts.max_rotation_deg, opts.max_rotation_deg))
    centre = (float(rng.uniform(0.3, 0.7) * w), float(rng.uniform(0.3, 0.7) * h))
    m = cv2.getRotationMatrix2D(centre, angle, scale)
    out_w, out_h = int(rng.integers(w // 2, w + 1)), int(rng.integers(h // 2, h + 1))
    m[:, 2] += (out_w / 2 - centre[0], out_h / 2 - centre[1])
    warped = cv2.warpAffine(
        image, m, (out_w, out_h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT
    )
    sigma = float(rng.uniform(0.0, opts.max_blur_sigma_px))
    if sigma > 0.3:
        warped = cv2.GaussianBlur(warped, (0, 0), sigma)
    gain, offset = float(rng.uniform(0.6, 1.4)), float(rng.uniform(-40, 40))
    return np.clip(warped.astype(np.float32) * gain + offset, 0, 255).astype(np.uint8)


def default_training_images(opts: AugmentOptions | None = None) -> Iterator[np.ndarray]:
    """The default vocabulary's training images: each photo, then its random variants."""
    opts = opts or AugmentOptions()
    rng = np.random.default_rng(opts.seed)
    for _, photo in skimage_photos():
        yield photo
        for _ in range(opts.variants_per_image):
            yield augment(photo, rng, opts)


def expand_image_inputs(inputs: Sequence[str]) -> tuple[list[Path], list[Path]]:
    """Split command-line inputs into (image files, sequence paths).

    An input is a glob, an image file, a folder of images (searched recursively), or anything
    else that :func:`datasets.open.open_sequence` can open (MCAP file, EuRoC folder ...).
    """
    images: list[Path] = []
    sequences: list[Path] = []
    for item in inputs:
        matches = sorted(Path(p) for p in glob.glob(item)) if glob.has_magic(item) else [Path(item)]
        if not matches:
            raise InputError(f"{item}: matches no file")
        for path in matches:
            if path.is_file() and path.suffix.lower() in IMAGE_SUFFIXES:
                images.append(path)
            elif path.is_dir():
                found = sorted(
                    p for p in path.rglob("*") if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file()
                )
                # A folder of plain images trains as images; anything else is a sequence.
                if found and not _looks_like_sequence(path):
                    images.extend(found)
                else:
                    sequences.append(path)
            elif path.exists():
                sequences.append(path)
            else:
                raise InputError(f"{path}: no such file or folder")
    return images, sequences


def _looks_like_sequence(folder: Path) -> bool:
    """EuRoC/TUM-VI ASL layout (mav0/ or cam0/data.csv) is a sequence, not loose images."""
    return (folder / "mav0").is_dir() or (folder / "cam0" / "data.csv").is_file()


def read_image_gray(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise InputError(f"{path}: cannot read image")
    return img


def sequence_left_images(path: Path, every_nth: int) -> Iterator[np.ndarray]:
    """Every Nth left image of a sequence (lazy import of the sequence readers)."""
    from datasets.open import open_sequence  # written by another module; imported lazily

    seq = open_sequence(path)
    for index in range(0, seq.num_frames, max(every_nth, 1)):
        yield seq.frame(index).left


def descriptors_of(images: Iterator[np.ndarray], max_features: int) -> Iterator[np.ndarray]:
    """ORB descriptors (n, 32) uint8 of each image."""
    for img in images:
        yield detect_orb(img, max_features=max_features).descriptors


@dataclass(frozen=True)
class VocabTrainOptions:
    """Parameters of a vocabulary training run."""

    branching: int = 10
    """k: children per node."""
    levels: int = 5
    """L: tree depth; up to k^L words."""
    max_features: int = 1000
    """ORB features per training image."""
    every_nth: int = 10
    """For sequences: use every Nth left frame."""
    seed: int = 0


def train_vocabulary(
    inputs: Sequence[str], opts: VocabTrainOptions, default_set: bool = False
) -> tuple[Vocabulary, int, int]:
    """Train on image files/folders/globs and sequences (and/or the default photo set).

    Returns (vocabulary, number of images, number of descriptors).
    """
    from tqdm import tqdm

    images, sequences = expand_image_inputs(inputs) if inputs else ([], [])
    if not images and not sequences and not default_set:
        raise InputError("nothing to train on: give image files/folders/sequences or --default")

    def all_images() -> Iterator[np.ndarray]:
        if default_set:
            yield from default_training_images(AugmentOptions(seed=opts.seed))
        for path in images:
            yield read_image_gray(path)
        for seq in sequences:
            yield from sequence_left_images(seq, opts.every_nth)

    descs = [
        d
        for d in tqdm(
            descriptors_of(all_images(), opts.max_features), desc="ORB", unit="img", leave=False
        )
        if len(d)
    ]
    total = int(sum(len(d) for d in descs))
    if total == 0:
        raise InputError("no ORB features found in the training images")
    with tqdm(total=total * opts.levels, desc="vocabulary", unit="desc", leave=False) as bar:
        vocab = Vocabulary.train(
            descs, opts.branching, opts.levels, seed=opts.seed, progress=bar.update
        )
    return vocab, len(descs), total
