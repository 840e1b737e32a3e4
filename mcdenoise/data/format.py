"""Data format v1: one image on disk, its per-sample store, and the one reader and writer.

One image is a folder::

    meta.json       ImageMeta + format version + which files exist
    samples.bin     per-sample buffers (optional): tiled, memory-mappable, JSON header
    noisy.exr       per-pixel mean <name> and variance of the mean <name>_variance per channel
    reference.exr   converged reference (optional): radiance, maybe diffuse/specular/albedo

``samples.bin`` layout (all little-endian)::

    0   8 bytes   magic b"MCDSAMPL"
    8   uint32    format version (1)
    12  uint32    0 (reserved)
    16  uint64    n = length of the JSON header in bytes
    24  n bytes   JSON header (UTF-8), padded with spaces up to the first data section
    then, for each channel at the page-aligned offset its header entry gives, an array of shape
    (tiles_y, tiles_x, spp, C, tile, tile) in its dtype (float32, or float16 for half_ok channels)

Pixel rows and columns are cut into ``tile x tile`` tiles (32 by default: 4 KiB per sample and
component in float32, one page); the image is zero-padded to whole tiles. A crop reads only the
tiles it overlaps and, within a tile, only the requested samples: every read is a contiguous run.

Where each part lives (this module re-exports every name, so ``mcdenoise.data.format`` imports
keep working):

* :mod:`~mcdenoise.data.meta`: ``ImageMeta`` (meta.json), file names, version, JSON documents;
* :mod:`~mcdenoise.data.samples_header`: the samples.bin prefix and header layout;
* :mod:`~mcdenoise.data.writer`: ``SampleWriter``, ``write_image``;
* :mod:`~mcdenoise.data.reader`: ``SampleReader``;
* :mod:`~mcdenoise.data.image_folder`: ``ImageFolder``, ``read_image``;
* :mod:`~mcdenoise.data.stats`: ``pixel_stats``; :mod:`~mcdenoise.data.finite`: ``check_finite``.
"""

from __future__ import annotations

from mcdenoise.data.finite import check_finite
from mcdenoise.data.image_folder import ImageFolder, read_image
from mcdenoise.data.meta import (
    DEFAULT_TILE,
    FORMAT_VERSION,
    META_FILE,
    NOISY_FILE,
    REFERENCE_FILE,
    SAMPLES_FILE,
    ImageMeta,
    read_json_document,
)
from mcdenoise.data.reader import SampleReader
from mcdenoise.data.samples_header import MAGIC
from mcdenoise.data.stats import pixel_stats
from mcdenoise.data.writer import SampleWriter, write_image

__all__ = [
    "FORMAT_VERSION",
    "ImageMeta",
    "write_image",
    "SampleWriter",
    "SampleReader",
    "ImageFolder",
    "read_image",
    "pixel_stats",
    "check_finite",
    "SAMPLES_FILE",
    "NOISY_FILE",
    "REFERENCE_FILE",
    "META_FILE",
    "DEFAULT_TILE",
    "read_json_document",
    "MAGIC",
]
