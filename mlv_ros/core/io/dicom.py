# Copyright 2026 The mlv_ros authors
#
# Licensed under the Apache License, Version 2.0 (the "License");
# you may not use this file except in compliance with the License.
# You may obtain a copy of the License at
#
#     http://www.apache.org/licenses/LICENSE-2.0
#
# Unless required by applicable law or agreed to in writing, software
# distributed under the License is distributed on an "AS IS" BASIS,
# WITHOUT WARRANTIES OR CONDITIONS OF ANY KIND, either express or implied.
# See the License for the specific language governing permissions and
# limitations under the License.

"""
DICOM in and out for tagged cine MR: one file per image, one series per slice location.

Writing (:func:`write_study_dicom`): MR Image Storage, Explicit VR Little Endian, uint16 pixels
with ``RescaleSlope`` mapping back to the simulator's float intensities, and the geometry,
timing and identification attributes listed in the issue (IPP/IOP/PixelSpacing/SliceThickness,
TriggerTime in ms, CardiacNumberOfImages, NominalInterval, InstanceNumber = phase + 1,
SeriesDescription naming SA/LA). Keyword options vary what scanners vary: 8/12/16 stored bits,
any RescaleSlope/RescaleIntercept or none, the SA stack in one multi-slice series, InstanceNumber
running across slices, random file names in nested folders.

Reading (:func:`read_dicom_dir`): every file under a directory (recursive, any name; directory
symlinks followed, each folder once, so a link loop ends; hidden and system files skipped) is
tried; per-file problems are collected as ``(path, reason)`` while everything valid loads. Each
file is checked before its pixels are read: a Part 10 header that is complete and not a DICOMDIR
(an index: ignored with a reason, its files being read directly), a transfer syntax that matches
how the pixels are stored and that an installed plugin decodes (otherwise the reason names the
package), greyscale frames (colour refused, planar configuration included in the reason) of at
most ``max_pixels`` each, one per file or an Enhanced multi-frame image (Enhanced MR, Legacy
Converted Enhanced MR: one file per cine, per stack or per frame; each frame's plane position and
orientation, pixel measures, rescale, trigger time and temporal position come from its per-frame
functional groups, then the shared ones, then the dataset, see :class:`_FrameView`), with
consistent Rows/Columns/BitsAllocated/BitsStored/HighBit/
PixelRepresentation and a pixel data length to match, and plane geometry that is finite, unit,
orthogonal and positive (contradictions are refused, not repaired); then float pixels must be
finite and the rescale usable. Pixels of any stored type (u)int8/16/32, float32/64 are converted
once to the working type (:data:`WORKING_DTYPES`): MONOCHROME1 inverted, rescale applied, uint8/
uint16 kept when there is no rescale, float32 otherwise. Duplicate instances are skipped, and a
cine missing phases (fewer images than CardiacNumberOfImages) keeps its phase indices and is
reported in ``warnings``. Images are grouped by series and plane (a cine), phases ordered by
TriggerTime then InstanceNumber. Then the study is chosen (:func:`read_dicom_dir`, Notes): cines
grouped by StudyInstanceUID and FrameOfReferenceUID, the group with the most MR cines whose ED
image shows a tag grid in its spectrum taken, else the one whose cines share a grid in windows
most clearly (tags on the heart alone, noise-relative; a study of one family of tag lines is
found, then refused: intersections needed; or the one asked for), its MR cines used (one that
fails the tag test only where no tagged cine holds its place and it was acquired like them, with
a warning), a slice acquired twice given by its later series, every cine given the study's phase
count (by nearest trigger time, or left out); every series not used is listed once with its
reason. Each used plane is classified from geometry alone: the largest group of parallel planes at
distinct positions is the short-axis stack, every other plane is long-axis. The long axis is
estimated from the LA planes' common line (or the SA normal), oriented apex → base with the
anatomical prior that the base lies right-posterior-superior of the apex (LPS ``(−1, 1, 1)`` side).
"""

from __future__ import annotations

from collections import Counter, defaultdict
from dataclasses import dataclass, field
import datetime
import math
import os
from pathlib import Path
import warnings

from mlv_ros.core.geometry import SliceGeometry
from mlv_ros.core.types import (
    Frame,
    TAGS_GRID,
    TAGS_LINE_PAIR,
    TAGS_LINES,
    VIEW_LA,
    VIEW_NAMES,
    VIEW_SA,
)
import numpy as np
import pydicom
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.errors import InvalidDicomError
from pydicom.multival import MultiValue
from pydicom.uid import ExplicitVRLittleEndian, MRImageStorage
from pydicom.valuerep import DSfloat

#: Stored value = round(intensity · PIXEL_SCALE); RescaleSlope = 1 / PIXEL_SCALE.
PIXEL_SCALE = 1000.0
_GEOMETRY_TAGS = ('ImagePositionPatient', 'ImageOrientationPatient', 'PixelSpacing')
_PIXEL_TAGS = ('PixelData', 'FloatPixelData', 'DoubleFloatPixelData')
#: Default :func:`read_dicom_dir` size limit, pixels (Rows × Columns).
DEFAULT_MAX_PIXELS = 4096 * 4096
# Unit length / orthogonality slack of ImageOrientationPatient (written to ~6 digits by scanners).
_IOP_TOL = 1e-2
_DEFER_BYTES = 256 * 1024  # values larger than this stay on disk until the header is checked
_UNDEFINED_LENGTH = 0xFFFFFFFF
#: Where an Enhanced frame's trigger time is looked for, first found wins (ms from the R wave).
_TRIGGER_KEYWORDS = (
    'NominalCardiacTriggerDelayTime',
    'TriggerTime',
    'ActualCardiacTriggerDelayTime',
)
#: A multi-frame file may hold at most this many times max_pixels pixels in all its frames.
_MAX_FILE_FRAMES_PIXELS = 512
_PARALLEL_COS = np.cos(np.radians(5.0))
_BASE_SIDE = np.array([-1.0, 1.0, 1.0]) / np.sqrt(3.0)


#: Pixel types of :func:`read_dicom_dir`'s frames, each publishable as a sensor_msgs/Image
#: (mono8, mono16, 32FC1): unsigned 8/16-bit stored values without a rescale stay as they are,
#: everything else (signed, 32-bit, float, or any rescale) is float32 (see ``_working_pixels``).
WORKING_DTYPES = (np.dtype(np.uint8), np.dtype(np.uint16), np.dtype(np.float32))
_KEPT_DTYPES = (np.dtype(np.uint8), np.dtype(np.uint16))
_COLOUR_PHOTOMETRIC = (
    'RGB',
    'PALETTE COLOR',
    'YBR_FULL',
    'YBR_FULL_422',
    'YBR_PARTIAL_420',
    'YBR_PARTIAL_422',
    'YBR_ICT',
    'YBR_RCT',
    'ARGB',
    'CMYK',
    'HSV',
)
_LIBJPEG = 'pylibjpeg with pylibjpeg-libjpeg'
_OPENJPEG = 'pylibjpeg with pylibjpeg-openjpeg'
# The PyPI packages that give pydicom a decoder for each compressed syntax (versions pinned in
# requirements/base.txt).
_DECODER_PACKAGES = {
    pydicom.uid.JPEGBaseline8Bit: f'{_LIBJPEG} (or Pillow)',
    pydicom.uid.JPEGExtended12Bit: f'{_LIBJPEG} (Pillow decodes 8-bit samples only)',
    pydicom.uid.JPEGLossless: _LIBJPEG,
    pydicom.uid.JPEGLosslessSV1: _LIBJPEG,
    pydicom.uid.JPEGLSLossless: f'pyjpegls (or {_LIBJPEG})',
    pydicom.uid.JPEGLSNearLossless: f'pyjpegls (or {_LIBJPEG})',
    pydicom.uid.JPEG2000Lossless: f'{_OPENJPEG} (or Pillow built with OpenJPEG)',
    pydicom.uid.JPEG2000: f'{_OPENJPEG} (or Pillow built with OpenJPEG)',
    pydicom.uid.HTJ2KLossless: _OPENJPEG,
    pydicom.uid.HTJ2KLosslessRPCL: _OPENJPEG,
    pydicom.uid.HTJ2K: _OPENJPEG,
    pydicom.uid.RLELossless: "numpy (pydicom's own decoder), or pylibjpeg with pylibjpeg-rle",
}
# Syntaxes no pydicom plugin decodes: what to do instead (matched on the UID's name).
_NO_DECODER_HINTS = (
    (
        'JPEG 2000 Part 2',
        'no PyPI plugin decodes it for pydicom: convert the files first (e.g. GDCM '
        'gdcmconv --raw)',
    ),
    (
        'JPIP',
        'the pixels are not in the file (a JPIP server reference): retrieve the images themselves',
    ),
    ('MPEG', 'a video, not images: export the series as images'),
    ('HEVC', 'a video, not images: export the series as images'),
    ('SMPTE', 'a video or audio stream, not images: export the series as images'),
)
#: Names skipped without a report (operating-system and file-manager droppings); so is every
#: name starting with "." (hidden files and folders, macOS "._*" resource forks).
_SYSTEM_NAMES = frozenset(
    {
        'thumbs.db',
        'ehthumbs.db',
        'desktop.ini',
        '__macosx',
        '$recycle.bin',
        'system volume information',
        'lost+found',
    }
)


class DicomReadError(ValueError):
    """Nothing usable under the directory; ``problems`` lists ``(path, reason)`` per file."""

    def __init__(self, message: str, problems: list[tuple[str, str]] | None = None):
        super().__init__(message)
        self.problems = list(problems or [])


# ---------------------------------------------------------------------------------- writing
def _ds(v: float) -> DSfloat:
    return DSfloat(float(v), auto_format=True)


#: ``write_study_dicom`` choices: how SA slices map to series, how InstanceNumber runs, file names.
SA_SERIES = ('per_slice', 'single')
INSTANCE_NUMBERS = ('per_slice', 'across_slices')
FILE_NAMES = ('ordered', 'random')
BITS_STORED = (8, 12, 16)


def _random_paths(out: Path, n: int, seed: int) -> list[Path]:
    """Draw ``n`` distinct paths 1–3 folders deep under ``out`` (hex names, mixed suffixes)."""
    rng = np.random.default_rng(seed)
    pools = [[f'{rng.integers(1 << 24):06x}' for _ in range(3)] for _ in range(3)]
    paths: list[Path] = []
    seen: set[Path] = set()
    while len(paths) < n:
        depth = int(rng.integers(1, 4))
        folder = out.joinpath(*(pools[k][int(rng.integers(3))] for k in range(depth)))
        name = f'{int(rng.integers(1 << 62)):016x}' + ('', '.dcm', '.IMA')[int(rng.integers(3))]
        path = folder / name  # never a folder's name: those have 6 hex digits, files 16
        if path not in seen:
            seen.add(path)
            paths.append(path)
    return paths


def write_study_dicom(
    study,
    out_dir,
    pixel_scale: float = PIXEL_SCALE,
    progress=None,
    *,
    bits_stored: int = 16,
    rescale: bool = True,
    rescale_intercept: float = 0.0,
    sa_series: str = 'per_slice',
    instance_numbers: str = 'per_slice',
    file_names: str = 'ordered',
    names_seed: int = 0,
    series_offset: int = 0,
) -> list[Path]:
    """
    Write every frame of a simulated study as one DICOM file.

    Default layout: ``out_dir/<SA|LA>_<index>/IM_<phase+1>.dcm``, one series per slice location,
    InstanceNumber = phase + 1; any layout reads back the same way (:func:`read_dicom_dir`).

    Parameters
    ----------
    study : mlv_ros.core.sim.Study
        Simulated study (float images; myocardium M0 = 1).
    out_dir : str or Path
        Created if needed.
    pixel_scale : float
        Stored units per intensity unit: stored = round((intensity − rescale_intercept) ·
        pixel_scale), clipped to the stored range ``0 .. 2**bits_stored − 1``.
    progress : callable, optional
        ``progress(done, total)`` after each file.
    bits_stored : {8, 12, 16}
        BitsStored (8 → BitsAllocated 8, else 16), unsigned.
    rescale : bool
        Write RescaleSlope = 1/pixel_scale and RescaleIntercept = rescale_intercept (the reader
        then returns intensities); False writes neither, the stored values being the image
        (``rescale_intercept`` must then be 0).
    rescale_intercept : float
        Intensity of stored value 0 (intensity units, ≤ 0 keeps every intensity ≥ 0 in range).
    sa_series : {"per_slice", "single"}
        One series per SA slice, or the whole SA stack in one multi-slice series (one
        SeriesInstanceUID/SeriesNumber, description ``"tagged SA stack"``). LA planes are always
        one series each. Series are numbered in ``study.keys`` order.
    instance_numbers : {"per_slice", "across_slices"}
        InstanceNumber = phase + 1 in every slice, or running on across the slices (slice k of
        a multi-slice series, or of the whole study when every slice is its own series, gets
        ``k · num_phases + phase + 1``).
    file_names : {"ordered", "random"}
        The default layout, or random hex names 1–3 random folders deep (``names_seed``).
    names_seed : int
        Seeds the random names.
    series_offset : int
        Added to every SeriesNumber (a second series of the same slices, e.g. the second
        single-line series of a line pair, numbered after the first).

    Returns
    -------
    list of Path
        The written files, in frame order.

    Raises
    ------
    ValueError
        An option outside its choices, a non-positive ``pixel_scale``, or an intercept without
        a rescale.

    """
    _check_write_options(
        bits_stored, sa_series, instance_numbers, file_names, pixel_scale, rescale,
        rescale_intercept,
    )
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    series_number, series_uid, descriptions, position = _series_layout(
        study, sa_series, int(series_offset)
    )
    total = len(study.frames)
    names = _random_paths(out, total, names_seed) if file_names == 'random' else None
    paths = []
    for n, fr in enumerate(study.frames):
        key = (fr.view, fr.slice_index)
        instance = None
        if instance_numbers == 'across_slices':
            instance = position[key] * int(fr.num_phases) + int(fr.phase_index) + 1
        ds = frame_to_dataset(
            fr,
            pixel_scale=pixel_scale,
            study_uid=study.study_uid,
            frame_of_reference_uid=study.frame_of_reference_uid,
            series_number=series_number[key] + int(series_offset),
            description=descriptions[key],
            patient_name=f'MLV^{study.preset["name"]}',
            bits_stored=bits_stored,
            rescale=rescale,
            rescale_intercept=rescale_intercept,
            instance_number=instance,
            series_uid=series_uid.get(key),
        )
        if names is None:
            d = out / f'{VIEW_NAMES[fr.view]}_{fr.slice_index:02d}'
            path = d / f'IM_{fr.phase_index + 1:04d}.dcm'
        else:
            path = names[n]
        path.parent.mkdir(parents=True, exist_ok=True)
        ds.save_as(path, enforce_file_format=True)
        paths.append(path)
        if progress is not None:
            progress(n + 1, total)
    return paths


def _check_write_options(
    bits_stored, sa_series, instance_numbers, file_names, pixel_scale, rescale, rescale_intercept
) -> None:
    """Refuse write_study_dicom options outside their choices (its parameters; ValueError)."""
    if bits_stored not in BITS_STORED:
        raise ValueError(f'bits_stored must be one of {BITS_STORED}, got {bits_stored!r}')
    for name, v, choices in (
        ('sa_series', sa_series, SA_SERIES),
        ('instance_numbers', instance_numbers, INSTANCE_NUMBERS),
        ('file_names', file_names, FILE_NAMES),
    ):
        if v not in choices:
            raise ValueError(f'{name} must be one of {choices}, got {v!r}')
    if not (np.isfinite(pixel_scale) and pixel_scale > 0):
        raise ValueError(
            f'pixel_scale must be a positive number of stored units per intensity '
            f'unit, got {pixel_scale}'
        )
    if not np.isfinite(rescale_intercept) or (not rescale and rescale_intercept != 0.0):
        raise ValueError(
            f'rescale_intercept must be finite, and 0 without a rescale; got {rescale_intercept}'
        )


def _series_layout(study, sa_series: str, offset: int = 0) -> tuple[dict, dict, dict, dict]:
    """
    Give each series its number, UID and description, and each slice its place in its series.

    ``offset``: :func:`write_study_dicom`'s ``series_offset`` (a second series of the same
    slices: its SA stack gets a UID of its own).

    Returns
    -------
    series_number, series_uid, descriptions, position : dict
        By ``(view, slice_index)`` key: SeriesNumber, SeriesInstanceUID (where not the
        frame's own), SeriesDescription, and the slice's place in its series' numbering.

    """
    keys = study.keys
    series_number = {key: i + 1 for i, key in enumerate(keys)}
    series_uid: dict = {}
    descriptions = {
        key: study.descriptions.get(key, f'tagged {VIEW_NAMES[key[0]]} {key[1]}') for key in keys
    }
    position = {key: i for i, key in enumerate(keys)}  # slice's place in its series' numbering
    if sa_series == 'single':
        sa_keys = [k for k in keys if k[0] == VIEW_SA]
        extra = [f'series offset {offset}'] if offset else []
        stack_uid = pydicom.uid.generate_uid(entropy_srcs=[study.study_uid, 'SA stack', *extra])
        others = [k for k in keys if k[0] != VIEW_SA]
        series_number = {k: 1 for k in sa_keys} | {k: i + 2 for i, k in enumerate(others)}
        series_uid = {k: stack_uid for k in sa_keys}
        descriptions.update({k: 'tagged SA stack' for k in sa_keys})
        position = {k: i for i, k in enumerate(sa_keys)} | {k: 0 for k in others}
    return series_number, series_uid, descriptions, position


def frame_to_dataset(
    frame: Frame,
    pixel_scale: float = PIXEL_SCALE,
    study_uid: str = '',
    frame_of_reference_uid: str = '',
    series_number: int = 1,
    description: str = '',
    patient_name: str = 'MLV^Phantom',
    *,
    bits_stored: int = 16,
    rescale: bool = True,
    rescale_intercept: float = 0.0,
    instance_number: int | None = None,
    series_uid: str | None = None,
) -> Dataset:
    """
    DICOM dataset (MR Image Storage) of one frame; see the module docstring for the tags.

    Float images are stored as ``round((image − rescale_intercept) · pixel_scale)``, clipped to
    ``0 .. 2**bits_stored − 1`` (uint8 for 8 bits, else uint16), with ``RescaleSlope =
    1/pixel_scale`` and ``RescaleIntercept = rescale_intercept`` unless ``rescale`` is False;
    integer images of the stored type (uint8 for 8 bits, else uint16) are stored as they are
    (slope 1). ``instance_number`` defaults to
    phase + 1, ``series_uid`` to the frame's.

    Raises
    ------
    ValueError
        Not a 2-D image, an unsupported ``bits_stored``, or integer pixels that do not fit it.

    """
    stored, slope, inter = _stored_pixels(frame.image, pixel_scale, bits_stored, rescale_intercept)
    sop_uid = pydicom.uid.generate_uid(
        entropy_srcs=[frame.series_uid, str(frame.phase_index), str(frame.slice_index)]
    )
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = MRImageStorage
    meta.MediaStorageSOPInstanceUID = sop_uid
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = Dataset()
    ds.file_meta = meta
    ds.SOPClassUID = MRImageStorage
    ds.SOPInstanceUID = sop_uid
    ds.StudyInstanceUID = study_uid or pydicom.uid.generate_uid()
    ds.SeriesInstanceUID = series_uid or frame.series_uid or pydicom.uid.generate_uid()
    ds.FrameOfReferenceUID = frame_of_reference_uid or pydicom.uid.generate_uid()
    ds.Modality = 'MR'
    ds.Manufacturer = 'mlv_ros simulator'
    ds.PatientName = patient_name
    ds.PatientID = 'MLV-PHANTOM'
    ds.StudyDescription = 'Simulated tagged cine MR (SPAMM)'
    ds.SeriesDescription = description
    ds.SeriesNumber = int(series_number)
    ds.InstanceNumber = (
        int(frame.phase_index) + 1 if instance_number is None else int(instance_number)
    )
    ds.ImageType = ['DERIVED', 'PRIMARY', 'TAGGING']
    ds.ScanningSequence = 'GR'
    ds.SequenceVariant = 'SP'
    ds.MRAcquisitionType = '2D'
    _set_timing_and_geometry(ds, frame)
    ds.Rows, ds.Columns = stored.shape
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = 'MONOCHROME2'
    ds.BitsAllocated = 8 if bits_stored == 8 else 16
    ds.BitsStored = bits_stored
    ds.HighBit = bits_stored - 1
    ds.PixelRepresentation = 0
    if rescale:
        ds.RescaleIntercept = _ds(inter)
        ds.RescaleSlope = _ds(slope)
        ds.RescaleType = 'US'
    ds.WindowCenter = _ds(0.6 * pixel_scale)
    ds.WindowWidth = _ds(1.2 * pixel_scale)
    ds.PixelData = np.ascontiguousarray(stored).tobytes()
    return ds


def _stored_pixels(
    image, pixel_scale: float, bits_stored: int, rescale_intercept: float
) -> tuple[np.ndarray, float, float]:
    """
    Return an image's stored values, RescaleSlope and RescaleIntercept (see frame_to_dataset).

    Parameters
    ----------
    image : array_like
        2-D image: float intensities, or integers of the stored type (stored as they are).
    pixel_scale : float
        Stored units per intensity unit.
    bits_stored : int
        One of :data:`BITS_STORED`.
    rescale_intercept : float
        Intensity of stored value 0.

    Returns
    -------
    stored : np.ndarray
        uint8 for 8 bits, else uint16, within ``0 .. 2**bits_stored − 1``.
    slope, intercept : float

    Raises
    ------
    ValueError
        Not a 2-D image, an unsupported ``bits_stored``, or integer pixels that do not fit it.

    """
    img = np.asarray(image)
    if img.ndim != 2:
        raise ValueError(f'frame image must be 2-D, got shape {img.shape}')
    if bits_stored not in BITS_STORED:
        raise ValueError(f'bits_stored must be one of {BITS_STORED}, got {bits_stored!r}')
    top = (1 << bits_stored) - 1
    dtype = np.uint8 if bits_stored == 8 else np.uint16
    if img.dtype == dtype:
        if img.size and int(img.max()) > top:
            raise ValueError(
                f'integer pixels up to {int(img.max())} do not fit in {bits_stored} bits'
            )
        return img, 1.0, 0.0
    x = img.astype(np.float64)
    if rescale_intercept:
        x = x - float(rescale_intercept)
    stored = np.clip(np.rint(x * pixel_scale), 0, top).astype(dtype)
    return stored, 1.0 / pixel_scale, float(rescale_intercept)


def _set_timing_and_geometry(ds: Dataset, frame: Frame) -> None:
    """Write a frame's cardiac timing (ms) and plane geometry (mm) into its dataset."""
    g = frame.geometry
    ds.TriggerTime = _ds(frame.trigger_time * 1000.0)
    ds.NominalInterval = int(round(frame.cycle_duration * 1000.0))  # IS: whole ms
    ds.CardiacNumberOfImages = int(frame.num_phases)
    ds.ImagePositionPatient = [_ds(v) for v in g.image_position]
    ds.ImageOrientationPatient = [
        _ds(v) for v in np.concatenate([g.row_direction, g.column_direction])
    ]
    ds.PixelSpacing = [_ds(g.row_spacing), _ds(g.column_spacing)]
    ds.SliceThickness = _ds(g.slice_thickness)
    ds.SliceLocation = _ds(float(g.image_position @ g.normal))


# ---------------------------------------------------------------------------------- reading
@dataclass
class LongAxisEstimate:
    """
    Long axis recovered from the image geometry.

    Attributes
    ----------
    point : ndarray, shape (3,)
        A point on the axis, mm (LPS), near the centre of the SA stack.
    direction : ndarray, shape (3,)
        Unit vector, apex → base (anatomical prior, see module docstring).
    source : str
        ``"la_planes"`` (common line of ≥ 2 LA planes) or ``"sa_normal"``.

    """

    point: np.ndarray
    direction: np.ndarray
    source: str


@dataclass
class SeriesInfo:
    """One slice location's cine as read."""

    series_uid: str
    view: int
    slice_index: int
    description: str
    series_number: int
    geometry: SliceGeometry
    files: list[str]  # one per image, in phase order (a multi-frame file once per frame of it)
    # The second single-line series paired with this one (its files follow in ``files``), or "".
    line_series_uid: str = ''


@dataclass
class DicomReadResult:
    """
    Output of :func:`read_dicom_dir`; unpacks as ``frames, problems = result``.

    Attributes
    ----------
    frames : list of Frame
        Ordered by view (SA first), slice index, phase.
    problems : list of (str, str)
        ``(path, reason)`` for every file that was skipped, and once per series (its first file)
        for every series that was read but not used (another study, modality, one frame, not a
        cine, not tagged, a repeated acquisition, too few phases).
    series : list of SeriesInfo
    long_axis : LongAxisEstimate or None
    warnings : list of (str, str)
        ``(path, reason)`` for what loaded but is incomplete or was adapted: a cine missing
        phases (its frames keep their phase indices and the declared phase count), a slice
        acquired twice (the later kept), a cine with more phases than the study (matched by
        TriggerTime).
    study_uids : dict of str to int
        StudyInstanceUID → number of loaded images that declare it, most frequent first (images
        without one are not counted).
    study_uid : str
        StudyInstanceUID of the study the frames come from ("" when its images have none, or
        when no study was chosen: see ``choice``).
    studies : dict of str to int
        Every StudyInstanceUID under the folder ("" for images without one) → its number of
        tagged MR cines, most first.
    choice : str
        Which study was taken and why, in one sentence.
    complete : bool
        False when anything of the chosen study was left out (see ``left_out``).
    left_out : list of (str, str)
        ``(path, what and why)``: the chosen study's tagged cines not used (too few phases,
        another frame of reference), its cines missing phases, and its MR images that could not
        be read (those whose header still names the study; not its non-image objects).
    not_used : list of (str, str)
        The series read but not used, ``(first file, reason)`` once each (also in ``problems``).

    """

    frames: list[Frame]
    problems: list[tuple[str, str]]
    series: list[SeriesInfo] = field(default_factory=list)
    long_axis: LongAxisEstimate | None = None
    warnings: list[tuple[str, str]] = field(default_factory=list)
    study_uids: dict[str, int] = field(default_factory=dict)
    study_uid: str = ''
    studies: dict[str, int] = field(default_factory=dict)
    choice: str = ''
    complete: bool = True
    left_out: list[tuple[str, str]] = field(default_factory=list)
    not_used: list[tuple[str, str]] = field(default_factory=list)

    def __iter__(self):
        yield self.frames
        yield self.problems


@dataclass
class _Image:
    """
    One file that passed every per-file check, with the attributes the grouping needs parsed.

    Parsed so that nothing after :func:`_read_one` touches the raw, possibly malformed dataset.
    """

    path: str
    pixels: np.ndarray
    geometry: SliceGeometry
    series_uid: str = ''
    sop_uid: str = ''
    study_uid: str = ''
    description: str = ''
    series_number: int = 0
    instance: int | None = None
    trigger_ms: float = np.nan
    nominal_ms: float = np.nan
    cardiac_images: int | None = None
    modality: str = ''
    frame_of_reference_uid: str = ''
    #: When the series was acquired, for telling a repeat from the original: ``(has_date,
    #: seconds)`` (seconds since 0001-01-01 with a date, else since midnight), or None.
    acquired: tuple[bool, float] | None = None
    #: Frame number in a multi-frame (Enhanced) file, 1-based; 0 for a single-frame file.
    frame: int = 0
    #: Why the image is a Siemens MOSAIC (several slices tiled in one image), "" when it is not.
    mosaic: str = ''


class _Skip(Exception):
    """Raised inside :func:`_load_images`; its message is the file's reason in ``problems``."""


def _get(ds, name):
    """Return ``name``'s value or None; one pydicom cannot convert (DS ``"abc"``) raises _Skip."""
    try:
        return ds.get(name)
    except Exception as exc:  # pydicom converts lazily and raises whatever its parser raises
        raise _Skip(f'{name} is malformed ({type(exc).__name__}: {exc})') from None


def _optional(ds, name, kind):
    """
    Return an optional attribute as ``kind`` (int/float/str), or None when absent or malformed.

    An empty value counts as absent.
    """
    try:
        v = ds.get(name)
        if v is None or str(v).strip() == '':
            return None
        return kind(v)
    except Exception:  # optional timing/identity tags: a malformed one is treated as absent
        return None


def _required_int(ds, name) -> int:
    v = _get(ds, name)
    try:
        return int(v)
    except (TypeError, ValueError):
        raise _Skip(f'{name} is not an integer ({v!r})') from None


def _numbers(ds, name: str, n: int) -> np.ndarray:
    """``n`` finite floats from a multi-valued tag; anything else raises _Skip naming the tag."""
    v = _get(ds, name)
    vals = (
        list(v)
        if isinstance(v, (list, tuple, pydicom.multival.MultiValue))
        else ([] if v in (None, '') else [v])
    )
    if len(vals) != n:
        raise _Skip(f'{name} must hold {n} numbers, got {len(vals)}')
    try:
        out = np.array([float(x) for x in vals])
    except (TypeError, ValueError):
        raise _Skip(f'{name} holds a non-number ({vals!r})') from None
    if not np.all(np.isfinite(out)):
        raise _Skip(f'{name} is not finite: {out.tolist()}')
    return out


def _geometry(ds) -> SliceGeometry:
    """
    Return the validated plane geometry; contradictions are refused, not silently repaired.

    Scanners write ImageOrientationPatient to about 6 digits, so directions within
    ``_IOP_TOL`` of unit length and orthogonality are re-orthonormalised; anything further off
    (a non-unit or skewed orientation) is an error, as are non-positive spacings.
    """
    missing = [t for t in _GEOMETRY_TAGS if _get(ds, t) in (None, '')]
    if missing:
        raise _Skip(f'missing geometry tag(s): {", ".join(missing)}')
    ipp = _numbers(ds, 'ImagePositionPatient', 3)
    iop = _numbers(ds, 'ImageOrientationPatient', 6)
    ps = _numbers(ds, 'PixelSpacing', 2)
    row, col = iop[:3], iop[3:]
    for which, v in (('row', row), ('column', col)):
        norm = float(np.linalg.norm(v))
        if abs(norm - 1.0) > _IOP_TOL:
            raise _Skip(
                f'ImageOrientationPatient {which} direction has norm {norm:.6g}; a unit vector '
                'is required'
            )
    cos = float(row @ col) / float(np.linalg.norm(row) * np.linalg.norm(col))
    if abs(cos) > _PARALLEL_COS:
        raise _Skip('ImageOrientationPatient row and column directions are parallel')
    if abs(cos) > _IOP_TOL:
        raise _Skip(
            f'ImageOrientationPatient row and column directions are not orthogonal '
            f'(angle {np.degrees(np.arccos(np.clip(cos, -1, 1))):.2f} deg)'
        )
    if np.any(ps <= 0):
        raise _Skip(f'PixelSpacing must be two positive mm values, got {ps.tolist()}')
    thick = 0.0
    if _get(ds, 'SliceThickness') not in (None, ''):
        thick = float(_numbers(ds, 'SliceThickness', 1)[0])
        if thick < 0:
            raise _Skip(f'SliceThickness must be a positive number of mm, got {thick}')
    row = row / np.linalg.norm(row)
    col = col - (col @ row) * row
    col = col / np.linalg.norm(col)
    # SliceThickness is type 2 (may be empty); 0 or absent = unknown: take the in-plane spacing.
    return SliceGeometry(ipp, row, col, float(ps[0]), float(ps[1]), thick or float(min(ps)))


def _truncated_meta(path: str, meta) -> str | None:
    """Reason when the file ends inside its file meta group (as declared by its group length)."""
    glen = _optional(meta, 'FileMetaInformationGroupLength', int)
    size = os.path.getsize(path)
    if glen is not None and size < 132 + 12 + glen:
        return (
            f'truncated inside the file meta information ({size} bytes; its header alone '
            f'needs {144 + glen})'
        )
    return None


def _no_pixels_reason(ds) -> str:
    meta = getattr(ds, 'file_meta', None)
    # The file meta is complete by now (checked against its group length); the dataset's own
    # SOPClassUID may be the element a truncation cut short.
    sop = (_optional(meta, 'MediaStorageSOPClassUID', str) if meta else None) or _optional(
        ds, 'SOPClassUID', str
    )
    name = pydicom.uid.UID(sop).name if sop else ''
    if 'Image' in name or 'Rows' in ds:
        return f'no pixel data in an image object ({name or "Rows present"}): truncated file?'
    if not sop:
        return 'no pixel data and no SOP class (truncated or not an image)'
    return f'no pixel data (non-image DICOM: {name})'


def _check_encoding(ds, pixel_tag: str) -> tuple[int, int]:
    """Validate the Image Pixel module; returns (rows, columns)."""
    required = ['Rows', 'Columns', 'SamplesPerPixel', 'PhotometricInterpretation', 'BitsAllocated']
    if pixel_tag == 'PixelData':
        required += ['BitsStored', 'PixelRepresentation']
    missing = [t for t in required if _get(ds, t) in (None, '')]
    if missing:
        raise _Skip(f'missing image tag(s): {", ".join(missing)}')
    rows, cols = _required_int(ds, 'Rows'), _required_int(ds, 'Columns')
    if rows <= 0 or cols <= 0:
        raise _Skip(f'image has zero size (Rows {rows}, Columns {cols})')
    nframes = _get(ds, 'NumberOfFrames')
    if (
        nframes not in (None, '')
        and _required_int(ds, 'NumberOfFrames') != 1
        and not _enhanced(ds)
    ):
        raise _Skip(
            f'NumberOfFrames {nframes} without per-frame functional groups: one 2-D frame per '
            'file '
            f'expected, or an Enhanced (functional-group) multi-frame image'
        )
    _check_greyscale(ds)
    _check_bits(ds, pixel_tag)
    return rows, cols


def _check_greyscale(ds) -> None:
    """Refuse a colour image: tagged MR is greyscale, and colour grey levels are no intensities."""
    spp = _required_int(ds, 'SamplesPerPixel')
    photometric = str(_get(ds, 'PhotometricInterpretation')).strip()
    if spp < 1:
        raise _Skip(f'SamplesPerPixel {spp}: greyscale images (1 sample per pixel) expected')
    if spp > 1:
        # PlanarConfiguration (type 1 with several samples) is checked so the reason is exact;
        # either way the image is refused: tagged MR is greyscale, and a colour rendering's
        # grey levels are not the scanner's intensities. (With 1 sample per pixel it has no
        # meaning, and is ignored.)
        planar = _get(ds, 'PlanarConfiguration')
        if planar in (None, ''):
            layout = 'PlanarConfiguration missing (required with more than 1 sample per pixel)'
        elif _required_int(ds, 'PlanarConfiguration') not in (0, 1):
            layout = f'PlanarConfiguration {planar} invalid (0 or 1)'
        else:
            layout = (
                f'PlanarConfiguration {planar} = '
                f'{("colour-by-pixel", "colour-by-plane")[int(planar)]}'
            )
        raise _Skip(
            f'colour image (SamplesPerPixel {spp}, PhotometricInterpretation {photometric!r}, '
            f'{layout}): '
            f'greyscale images (1 sample per pixel) expected; export the series as MONOCHROME2'
        )
    if photometric in _COLOUR_PHOTOMETRIC:
        raise _Skip(
            f'colour image (PhotometricInterpretation {photometric!r} with SamplesPerPixel 1): '
            'greyscale '
            f'MONOCHROME1/2 expected; export the series as MONOCHROME2'
        )
    if photometric not in ('MONOCHROME1', 'MONOCHROME2'):
        raise _Skip(f'PhotometricInterpretation {photometric!r}: greyscale MONOCHROME1/2 expected')


def _check_bits(ds, pixel_tag: str) -> None:
    """Refuse bit depths and signs that contradict each other or the pixel data element."""
    bits = _required_int(ds, 'BitsAllocated')
    if pixel_tag != 'PixelData':
        want = 32 if pixel_tag == 'FloatPixelData' else 64
        if bits != want:
            raise _Skip(f'BitsAllocated {bits} contradicts {pixel_tag} ({want} expected)')
        return
    if bits not in (8, 16, 32):
        raise _Skip(f'BitsAllocated {bits}: 8, 16 or 32 expected for greyscale pixels')
    stored = _required_int(ds, 'BitsStored')
    if not 1 <= stored <= bits:
        raise _Skip(f'BitsStored {stored} outside 1..BitsAllocated ({bits})')
    if _get(ds, 'HighBit') not in (None, '') and _required_int(ds, 'HighBit') != stored - 1:
        raise _Skip(f'HighBit {ds.HighBit} must be BitsStored - 1 = {stored - 1}')
    sign = _required_int(ds, 'PixelRepresentation')
    if sign not in (0, 1):
        raise _Skip(f'PixelRepresentation {sign}: 0 (unsigned) or 1 (signed) expected')


def _working_pixels(ds, pixels: np.ndarray, tag: str) -> np.ndarray:
    """
    Convert stored pixel values to the working type (:data:`WORKING_DTYPES`) in one conversion.

    MONOCHROME1 (minimum = white) is inverted within the stored range (BitsStored and
    PixelRepresentation; a float image within its own min..max) so that, as in MONOCHROME2,
    bright means high signal; a reflection commutes with the linear rescale, so this equals
    inverting the rescaled values. Then ``RescaleSlope``/``RescaleIntercept`` apply. Unsigned
    8/16-bit values without a rescale keep their type; everything else becomes float32 (exact
    for every integer up to 2**24 in magnitude, so for all 8/16-bit types; 32-bit integers and
    float64 round to float32's 24-bit mantissa).
    """
    pixels = pixels.astype(pixels.dtype.newbyteorder('='), copy=False)  # big endian → native
    if pixels.dtype.kind == 'f':
        bad = pixels.size - int(np.count_nonzero(np.isfinite(pixels)))
        if bad:
            raise _Skip(f'{tag} has {bad} non-finite value(s) (NaN/inf)')
    elif pixels.dtype.kind not in 'iu':
        raise _Skip(f'pixel data decodes to {pixels.dtype}, not integer or float grey levels')
    stored = pixels.dtype
    if str(_get(ds, 'PhotometricInterpretation')).strip() == 'MONOCHROME1':
        if stored.kind == 'f':
            pixels = (float(pixels.min()) + float(pixels.max())) - pixels.astype(np.float64)
        else:
            bits = _required_int(ds, 'BitsStored')
            lo, hi = (
                (-(1 << (bits - 1)), (1 << (bits - 1)) - 1)
                if stored.kind == 'i'
                else (0, (1 << bits) - 1)
            )
            pixels = (lo + hi) - pixels.astype(np.int64)
    slope = (
        _numbers(ds, 'RescaleSlope', 1)[0] if _get(ds, 'RescaleSlope') not in (None, '') else 1.0
    )
    inter = (
        _numbers(ds, 'RescaleIntercept', 1)[0]
        if _get(ds, 'RescaleIntercept') not in (None, '')
        else 0.0
    )
    if slope == 0:
        raise _Skip('RescaleSlope is 0: every pixel would map to the intercept')
    if stored in _KEPT_DTYPES and slope == 1.0 and inter == 0.0:
        # Still inside the stored range after an inversion (pydicom masks to BitsStored).
        if pixels.size == 0 or (pixels.min() >= 0 and pixels.max() <= np.iinfo(stored).max):
            return pixels.astype(stored, copy=False)
    with np.errstate(over='ignore', invalid='ignore'):
        out = (pixels.astype(np.float64) * slope + inter).astype(np.float32)
    if not np.all(np.isfinite(out)):
        raise _Skip(
            'pixel values are not finite as float32 (overflow in the rescale or the float '
            'conversion)'
        )
    return out


def _decoder_missing(ts) -> str | None:
    """
    Say why pydicom cannot decode compressed pixel data of transfer syntax ``ts`` here.

    The message names what would decode it; None when a decoder plugin is installed.
    """
    try:
        decoder = pydicom.pixels.get_decoder(ts)
    except NotImplementedError:
        hint = next(
            (h for prefix, h in _NO_DECODER_HINTS if ts.name.startswith(prefix)),
            'convert the files to an uncompressed transfer syntax (e.g. dcmtk dcmdjpeg, '
            'gdcmconv --raw)',
        )
        return (
            f'transfer syntax {ts.name} ({ts}): pydicom {pydicom.__version__} has no '
            f'decoder for it; {hint}'
        )
    if decoder.is_available:
        return None
    need = _DECODER_PACKAGES.get(ts, 'a pydicom decoder plugin')
    return (
        f'transfer syntax {ts.name} ({ts}): no decoder plugin installed; install {need}, '
        f'versions as pinned in requirements/base.txt'
    )


def _dicomdir_reason(path: str, ds) -> str:
    """Say why a DICOMDIR is ignored: it indexes files, which the reader finds by walking."""
    try:
        records = list(ds.get('DirectoryRecordSequence') or [])
        ids = [
            r.ReferencedFileID
            for r in records
            if str(r.get('DirectoryRecordType', '')).strip() == 'IMAGE'
            and r.get('ReferencedFileID')
        ]
        parts = [[str(i)] if isinstance(i, str) else [str(x) for x in i] for i in ids]
        missing = sum(not os.path.isfile(os.path.join(os.path.dirname(path), *q)) for q in parts)
        listed = f'; it lists {len(parts)} image file(s)' + (
            f', {missing} of them missing' if missing else ''
        )
    except Exception:  # a damaged index changes nothing: the folder is walked anyway
        listed = ''
    return (
        f'DICOMDIR (media storage directory) ignored: every file under the folder is read '
        f'directly{listed}'
    )


def _load_images(path: str, max_pixels: int) -> list[_Image]:
    """
    Every per-file check, cheapest first; pixel bytes are only read once the header is sane.

    One image per frame: an Enhanced multi-frame file gives each frame with its functional groups
    (:func:`_frame_views`).
    """
    ds = _open_header(path)
    ts, tag = _check_header(path, ds)
    # The Image Pixel module first: pydicom resolves the pixel element's VR (OB or OW) from it.
    rows, cols = _check_encoding(ds, tag)
    encapsulated = _check_pixel_element(ds, ts, tag)
    nframes = _check_size(ds, rows, cols, max_pixels)
    views = _frame_views(ds, nframes) if _enhanced(ds) else [ds]
    geoms = []
    for k, view in enumerate(views):
        try:
            geoms.append(_geometry(view))
        except _Skip as why:
            raise _Skip(
                f'frame {k + 1} of {nframes}: {why}' if len(views) > 1 else str(why)
            ) from None
    bits = _required_int(ds, 'BitsAllocated')
    if not encapsulated:
        _check_pixel_length(ds, tag, rows * cols * bits // 8 * nframes, nframes)
    if encapsulated:
        missing = _decoder_missing(ts)
        if missing:
            raise _Skip(missing)
    try:
        pixels = ds.pixel_array
    except Exception as exc:  # decoders (pydicom's own, Pillow, ...) raise assorted types
        raise _Skip(
            f'pixel data unreadable (transfer syntax {ts.name}; {type(exc).__name__}: {exc})'
        ) from None
    want_shape = (nframes, rows, cols) if nframes > 1 else (rows, cols)
    if pixels.shape != want_shape:
        raise _Skip(
            f'pixel data decodes to shape {pixels.shape}, header says '
            f'{"x".join(map(str, want_shape))}'
        )
    if views[0] is ds:
        return [_image(path, ds, _working_pixels(ds, pixels, tag), geoms[0])]
    return _frame_images(path, views, geoms, pixels.reshape(nframes, rows, cols), tag)


def _open_header(path: str) -> Dataset:
    """Read a file's header, leaving large values (pixel data) on disk until it is checked."""
    if os.path.getsize(path) == 0:
        raise _Skip('empty file (0 bytes)')
    try:
        return pydicom.dcmread(path, defer_size=_DEFER_BYTES)
    except InvalidDicomError as exc:
        raise _Skip(f'not a DICOM file ({exc})') from None
    except Exception as exc:  # pydicom raises many types on damaged files
        try:
            ts = pydicom.filereader.read_file_meta_info(path).get('TransferSyntaxUID')
        except Exception:
            ts = None
        where = f', transfer syntax {pydicom.uid.UID(ts).name}' if ts else ''
        raise _Skip(
            f'unreadable DICOM: damaged or truncated ({type(exc).__name__}: {exc}{where})'
        ) from None


def _check_header(path: str, ds: Dataset) -> tuple[pydicom.uid.UID, str]:
    """
    Check that a file is an image with one pixel data element under a known transfer syntax.

    Parameters
    ----------
    path : str
        The file (a DICOMDIR's listed files are looked up next to it).
    ds : Dataset
        Its dataset as read by :func:`_open_header`.

    Returns
    -------
    ts : pydicom.uid.UID
        The transfer syntax.
    tag : str
        The keyword of the pixel data element (one of :data:`_PIXEL_TAGS`).

    Raises
    ------
    _Skip
        Why the file is not read.

    """
    meta = getattr(ds, 'file_meta', None) or Dataset()
    cut = _truncated_meta(path, meta)
    if cut:
        raise _Skip(cut)
    sop = _optional(meta, 'MediaStorageSOPClassUID', str) or _optional(ds, 'SOPClassUID', str)
    if sop == pydicom.uid.MediaStorageDirectoryStorage:
        raise _Skip(_dicomdir_reason(path, ds))
    ts = _optional(meta, 'TransferSyntaxUID', str)
    if not ts:
        raise _Skip(
            'no TransferSyntaxUID in the file meta information: damaged or truncated header'
        )
    ts = pydicom.uid.UID(ts)
    if len(ds) == 0:
        raise _Skip('no data elements after the file meta information: truncated or damaged')
    if not any(pydicom.datadict.dictionary_has_tag(t) for t in ds.keys()):
        raise _Skip(
            f'no standard data element decodes under the declared transfer syntax {ts.name}: '
            f'wrong transfer syntax or damaged dataset'
        )
    present = [t for t in _PIXEL_TAGS if t in ds]
    if not present:
        raise _Skip(_no_pixels_reason(ds))
    if len(present) > 1:
        raise _Skip(f'more than one pixel data element ({", ".join(present)}): ambiguous')
    if not ts.is_transfer_syntax:
        raise _Skip(f'unknown transfer syntax {ts}')
    return ts, present[0]


def _check_pixel_element(ds: Dataset, ts: pydicom.uid.UID, tag: str) -> bool:
    """Return whether the pixel data is encapsulated, refusing one its transfer syntax denies."""
    try:
        raw = ds.get_item(tag)
    except Exception as exc:  # pydicom resolves the VR and may convert the value here
        raise _Skip(f'{tag} element unreadable ({type(exc).__name__}: {exc})') from None
    encapsulated = getattr(raw, 'length', None) == _UNDEFINED_LENGTH or bool(
        getattr(raw, 'is_undefined_length', False)
    )
    if ts.is_compressed and not encapsulated:
        raise _Skip(
            f'transfer syntax {ts.name} declares compressed (encapsulated) pixel data, '
            f'but {tag} is stored uncompressed'
        )
    if encapsulated and not ts.is_compressed:
        raise _Skip(f'{tag} is encapsulated but the transfer syntax {ts.name} is uncompressed')
    return encapsulated


def _check_size(ds: Dataset, rows: int, cols: int, max_pixels: int) -> int:
    """Return the frame count, refusing an image or file too large to read (``max_pixels``)."""
    if rows * cols > max_pixels:
        raise _Skip(
            f'image declares {rows}x{cols} = {rows * cols} pixels, more than max_pixels = '
            f'{max_pixels}'
        )
    nframes = _optional(ds, 'NumberOfFrames', int) or 1
    if nframes < 1:
        raise _Skip(f'NumberOfFrames {nframes}: at least 1 expected')
    if nframes * rows * cols > _MAX_FILE_FRAMES_PIXELS * max_pixels:
        raise _Skip(
            f'{nframes} frames of {rows}x{cols} pixels: more than {_MAX_FILE_FRAMES_PIXELS} x '
            'max_pixels '
            f'= {_MAX_FILE_FRAMES_PIXELS * max_pixels} pixels in one file'
        )
    return nframes


def _check_pixel_length(ds: Dataset, tag: str, want: int, nframes: int) -> None:
    """Refuse native pixel data shorter or longer than the header's ``want`` bytes."""
    have = len(_get(ds, tag) or b'')
    if have < want:
        raise _Skip(
            f'pixel data unreadable: truncated, {have} of {want} bytes present '
            f'(Rows × Columns × BitsAllocated/8{" × NumberOfFrames" if nframes > 1 else ""})'
        )
    if have > want + 1:  # one byte of padding to an even length is legal
        raise _Skip(
            f'pixel data too long: {have} bytes for Rows × Columns × BitsAllocated/8'
            f'{" × NumberOfFrames" if nframes > 1 else ""} = {want} '
            f'(wrong Rows, Columns or BitsAllocated?)'
        )


def _frame_images(path: str, views, geoms, stack: np.ndarray, tag: str) -> list[_Image]:
    """
    Make an Enhanced file's frames images, each timed by its functional groups.

    Without a phase count, the largest TemporalPositionIndex stands for it.

    Parameters
    ----------
    path : str
        The file.
    views : list
        Each frame's view of the dataset (:func:`_frame_views`).
    geoms : list of SliceGeometry
        Each frame's geometry.
    stack : np.ndarray
        Decoded pixels, shape (frames, rows, cols).
    tag : str
        The pixel data element's keyword.

    Returns
    -------
    list of _Image

    """
    nframes = len(stack)
    out = []
    for k, (view, geom) in enumerate(zip(views, geoms)):
        try:
            out.append(_image(path, view, _working_pixels(view, stack[k], tag), geom, frame=k + 1))
        except _Skip as why:
            raise _Skip(f'frame {k + 1} of {nframes}: {why}') from None
    temporal = [_optional(view, 'TemporalPositionIndex', int) for view in views]
    if not any(i.cardiac_images for i in out) and all(t and t > 0 for t in temporal):
        for i in out:
            i.cardiac_images = max(temporal)
    return out


def _image(path: str, ds, pixels: np.ndarray, geom: SliceGeometry, frame: int = 0) -> _Image:
    """Build the :class:`_Image` of one checked frame (``ds``: the dataset or a frame's view)."""
    if frame:  # Enhanced: the frame's phase is its TemporalPositionIndex where it has one
        instance = _optional(ds, 'TemporalPositionIndex', int) or frame
        trigger = next(
            (
                t
                for t in (_optional(ds, k, float) for k in _TRIGGER_KEYWORDS)
                if t is not None and np.isfinite(t)
            ),
            None,
        )
        nominal = _optional(ds, 'RRIntervalTimeNominal', float) or _optional(
            ds, 'NominalInterval', float
        )
    else:
        instance = _optional(ds, 'InstanceNumber', int)
        trigger, nominal = (
            _optional(ds, 'TriggerTime', float),
            _optional(ds, 'NominalInterval', float),
        )
    return _Image(
        path=path,
        pixels=pixels,
        geometry=geom,
        series_uid=_optional(ds, 'SeriesInstanceUID', str) or '',
        sop_uid=_optional(ds, 'SOPInstanceUID', str) or '',
        study_uid=_optional(ds, 'StudyInstanceUID', str) or '',
        description=_optional(ds, 'SeriesDescription', str) or '',
        series_number=_optional(ds, 'SeriesNumber', int) or 0,
        instance=instance,
        trigger_ms=_finite_or_nan(trigger),
        nominal_ms=_finite_or_nan(nominal),
        cardiac_images=_optional(ds, 'CardiacNumberOfImages', int),
        modality=(_optional(ds, 'Modality', str) or '').strip().upper(),
        frame_of_reference_uid=_optional(ds, 'FrameOfReferenceUID', str) or '',
        acquired=_acquired(ds),
        frame=frame,
        mosaic='' if frame else _mosaic(ds),
    )


def _mosaic(ds) -> str:
    """
    Say why ``ds`` is a Siemens MOSAIC image ("" when nothing says so).

    ImageType value MOSAIC, or a NumberOfImagesInMosaic above 1 in the private SIEMENS MR HEADER
    (0019,xx0A) or in the CSA image header (0029,xx10, read with nibabel's CSA reader). A malformed
    private element counts as absent.
    """
    said = []
    image_type = _optional(
        ds,
        'ImageType',
        lambda v: [
            str(x).strip().upper()
            for x in (v if isinstance(v, (list, tuple, MultiValue)) else [v])
        ],
    )
    if image_type and 'MOSAIC' in image_type:
        said.append('ImageType ' + '\\'.join(image_type))
    n = None
    try:
        n = int(ds.private_block(0x0019, 'SIEMENS MR HEADER')[0x0A].value)
    except Exception:  # absent or malformed
        pass
    if not n:
        try:
            raw = ds.private_block(0x0029, 'SIEMENS CSA HEADER')[0x10].value
            if isinstance(raw, bytes) and b'NumberOfImagesInMosaic' in raw:
                from nibabel.nicom import csareader

                with warnings.catch_warnings():
                    warnings.simplefilter('ignore')
                    n = int(csareader.get_n_mosaic(csareader.read(raw)) or 0)
        except Exception:  # absent, or a CSA header nibabel cannot parse
            pass
    if n and n > 1:
        said.append(f'NumberOfImagesInMosaic {n}')
    return '; '.join(said)


def _enhanced(ds) -> bool:
    """
    Check for an Enhanced (functional-group) image.

    Enhanced MR, Legacy Converted Enhanced MR, and the like: per-frame attributes in
    PerFrameFunctionalGroupsSequence.
    """
    try:
        return 'PerFrameFunctionalGroupsSequence' in ds or 'SharedFunctionalGroupsSequence' in ds
    except Exception:
        return False


class _FrameView:
    """
    One frame of an Enhanced multi-frame dataset seen as a single-frame one.

    ``get(name)`` looks in the frame's per-frame functional groups, then the shared ones (each
    macro's first item: PlanePositionSequence, PlaneOrientationSequence, PixelMeasuresSequence,
    PixelValueTransformationSequence, CardiacSynchronizationSequence, FrameContentSequence,
    MRTimingAndRelatedParametersSequence, the Unassigned…ConvertedAttributesSequence of legacy
    conversions, …), then the dataset itself.
    """

    def __init__(self, ds, per_frame, shared):
        self._layers = [*_macro_items(per_frame), *_macro_items(shared), ds]

    def get(self, name, default=None):
        for layer in self._layers:
            v = layer.get(name)
            if v is not None:
                return v
        return default

    def __contains__(self, name) -> bool:
        return any(name in layer for layer in self._layers)


def _macro_items(group) -> list:
    """Return the first item of each sequence in functional group item ``group`` (may be None)."""
    if group is None:
        return []
    out = []
    for elem in group:
        if elem.VR == 'SQ' and len(elem.value):
            out.append(elem.value[0])
    return out


def _frame_views(ds, nframes: int) -> list[_FrameView]:
    """Return a :class:`_FrameView` per frame; a malformed functional group skips the file."""
    try:
        shared_seq = ds.get('SharedFunctionalGroupsSequence')
        per_seq = ds.get('PerFrameFunctionalGroupsSequence')
    except Exception as exc:
        raise _Skip(f'functional groups unreadable ({type(exc).__name__}: {exc})') from None
    shared = shared_seq[0] if shared_seq else None
    per = list(per_seq) if per_seq else []
    if per and len(per) != nframes:
        raise _Skip(
            f'PerFrameFunctionalGroupsSequence has {len(per)} item(s) for NumberOfFrames {nframes}'
        )
    if not per and nframes > 1:
        raise _Skip(
            f"NumberOfFrames {nframes} without PerFrameFunctionalGroupsSequence: each frame's "
            'position '
            f'and timing unknown'
        )
    return [_FrameView(ds, per[k] if per else None, shared) for k in range(nframes)]


def _dicom_seconds(date: str | None, time: str | None) -> tuple[bool, float] | None:
    """
    Parse DA + TM as ``(has_date, seconds)``; None when the time is absent or malformed.

    DA is ``YYYYMMDD``, TM ``HHMMSS.FFFFFF`` or ``HH:MM:SS``.
    """
    t = (time or '').strip().replace(':', '')
    try:
        secs = (
            int(t[0:2]) * 3600
            + (int(t[2:4]) * 60 if len(t) >= 4 else 0)
            + (float(t[4:]) if len(t) > 4 else 0.0)
        )
    except ValueError:
        return None
    d = (date or '').strip().replace('.', '')
    if len(d) == 8 and d.isdigit():
        try:
            return True, datetime.date(
                int(d[:4]), int(d[4:6]), int(d[6:])
            ).toordinal() * 86400.0 + secs
        except ValueError:
            pass
    return False, float(secs)


def _acquired(ds) -> tuple[bool, float] | None:
    """
    Return when the image's series was acquired.

    AcquisitionDateTime, AcquisitionDate/Time, else SeriesDate/Time (optional tags: a malformed one
    counts as absent).
    """
    dt = _optional(ds, 'AcquisitionDateTime', str)
    if dt and len(dt.strip()) > 8:
        got = _dicom_seconds(dt.strip()[:8], dt.strip()[8:].split('+')[0].split('-')[0])
        if got is not None:
            return got
    for date, time in (('AcquisitionDate', 'AcquisitionTime'), ('SeriesDate', 'SeriesTime')):
        got = _dicom_seconds(_optional(ds, date, str), _optional(ds, time, str))
        if got is not None:
            return got
    return None


def _unread_image_of(path: str, study_uid: str) -> bool:
    """
    Check whether a file that did not read is an MR image of study ``study_uid``.

    As far as its header still says. Not: non-image objects of the study such as presentation
    states, structured reports or key-object selections, images of another modality, or a header
    that does not read.
    """
    try:
        with warnings.catch_warnings():
            warnings.simplefilter('ignore')
            ds = pydicom.dcmread(
                path,
                stop_before_pixels=True,
                defer_size=_DEFER_BYTES,
                specific_tags=['StudyInstanceUID', 'Modality', 'SOPClassUID', 'Rows'],
            )
            if str(ds.get('StudyInstanceUID', '') or '').strip() != study_uid:
                return False
            modality = str(ds.get('Modality', '') or '').strip().upper()
            meta = getattr(ds, 'file_meta', None)
            sop = str(
                (meta.get('MediaStorageSOPClassUID') if meta is not None else None)
                or ds.get('SOPClassUID', '')
                or ''
            )
            image = 'Image' in pydicom.uid.UID(sop).name if sop else 'Rows' in ds
            return image and modality in ('', 'MR')
    except Exception:  # not DICOM, damaged: nothing says which study it was
        return False


def _finite_or_nan(v: float | None) -> float:
    return float(v) if v is not None and np.isfinite(v) else np.nan


def _read_one(
    path: str, max_pixels: int = DEFAULT_MAX_PIXELS
) -> tuple[list[_Image] | None, str | None]:
    """Load one file; returns (images, None), one per frame, or (None, reason)."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter('ignore')  # pydicom's warnings repeat what the reason says
            return _load_images(path, max_pixels), None
    except _Skip as why:
        return None, str(why)
    except MemoryError:
        raise
    except (
        Exception
    ) as exc:  # a gap in the checks above: still a per-file report (fuzz finds these)
        return None, f'unexpected error reading the file ({type(exc).__name__}: {exc})'


def _plane_key(img: _Image) -> tuple:
    g = img.geometry
    n = g.normal
    return (
        img.series_uid,
        tuple(np.round(np.concatenate([g.row_direction, g.column_direction]), 3)),
        round(float(g.image_position @ n), 1),
    )


def _unit(v):
    return v / np.linalg.norm(v)


def estimate_long_axis(
    sa: list[SliceGeometry], la: list[SliceGeometry], sa_centres: np.ndarray | None = None
) -> LongAxisEstimate | None:
    """
    Long axis from SA and LA plane geometry (see module docstring).

    Parameters
    ----------
    sa, la : list of SliceGeometry
        One geometry per SA slice / LA plane.
    sa_centres : ndarray, shape (len(sa), 3), optional
        Field-of-view centres of the SA images, mm: the axis point without LA planes, and the
        point on the LA common line to stay near. Default: the SA (else LA) IPPs' mean.

    Returns
    -------
    LongAxisEstimate or None
        None when there is no plane at all.

    """
    if not sa and not la:
        return None
    d_sa = None
    if sa:
        ns = np.array([g.normal for g in sa])
        ns = ns * np.sign(ns @ ns[0])[:, None]
        d_sa = _unit(ns.mean(axis=0))
    if sa_centres is not None and len(sa_centres):
        centre = np.mean(np.asarray(sa_centres, dtype=np.float64), axis=0)
    else:
        centre = np.mean([g.image_position for g in (sa or la)], axis=0)
    if len(la) >= 2:
        N = np.array([g.normal for g in la])
        _, sv, vt = np.linalg.svd(N)
        d = vt[-1]
        if d_sa is not None and abs(d @ d_sa) < np.cos(np.radians(30.0)):
            d, source = d_sa, 'sa_normal'
        else:
            source = 'la_planes'
        # Point on the LA planes' common line closest to the SA centre (weak pull along d).
        A = np.vstack([N, 1e-3 * np.eye(3)])
        b = np.concatenate([[n @ g.image_position for n, g in zip(N, la)], 1e-3 * centre])
        point = np.linalg.lstsq(A, b, rcond=None)[0]
        point = point + ((centre - point) @ d) * d
    elif d_sa is not None:
        d, source, point = d_sa, 'sa_normal', centre
    else:
        return None
    if d @ _BASE_SIDE < 0:
        d = -d
    return LongAxisEstimate(point=point, direction=_unit(d), source=source)


def _fov_centre(img: _Image) -> np.ndarray:
    rows, cols = img.pixels.shape
    return img.geometry.pixel_to_patient(np.array([(rows - 1) / 2.0, (cols - 1) / 2.0]))


def _list_files(root: Path) -> tuple[list[str], list[tuple[str, str]]]:
    """
    Every file under ``root`` in sorted path order, and ``(path, reason)`` for what is not read.

    Directory symlinks are followed and every real folder is walked once: the folders reached
    without a link first, then each linked folder in the order met, so a link to a folder already
    walked (a second way in, or one of its own ancestors: a loop) is reported, not walked again.
    Hidden names (starting with ".") and :data:`_SYSTEM_NAMES` are skipped silently; broken
    links, unreadable folders and special files (a FIFO would block the read) are reported.
    """
    files: list[str] = []
    problems: list[tuple[str, str]] = []
    walked: dict[tuple[int, int], str] = {}  # (st_dev, st_ino) of each folder walked → its path
    real, links = [str(root)], []
    while real or links:
        d = real.pop() if real else links.pop(0)
        try:
            st = os.stat(d)
            key = (st.st_dev, st.st_ino)
            if key in walked:
                target = os.path.realpath(d)
                parent = os.path.realpath(os.path.dirname(d))
                if parent == target or parent.startswith(target.rstrip(os.sep) + os.sep):
                    problems.append(
                        (
                            d,
                            f'directory symlink loop: leads back to {walked[key]}, its own '
                            f'ancestor; not followed',
                        )
                    )
                else:
                    what = 'directory symlink to a folder' if os.path.islink(d) else 'folder'
                    problems.append((d, f'{what} already read as {walked[key]}; not read twice'))
                continue
            walked[key] = d
            entries = sorted(os.scandir(d), key=lambda e: e.name)
        except OSError as exc:
            problems.append(
                (d, f'folder unreadable ({type(exc).__name__}: {exc.strerror or exc})')
            )
            continue
        subdirs = []
        for e in entries:
            if e.name.startswith('.') or e.name.lower() in _SYSTEM_NAMES:
                continue
            try:
                if e.is_dir():  # follows links
                    (links if e.is_symlink() else subdirs).append(e.path)
                elif e.is_file():
                    files.append(e.path)
                elif e.is_symlink():
                    problems.append(
                        (
                            e.path,
                            f'broken symbolic link (target {os.readlink(e.path)!r} '
                            f'does not exist)',
                        )
                    )
                else:
                    problems.append(
                        (e.path, 'not a regular file (FIFO, socket or device): not read')
                    )
            except OSError as exc:
                problems.append(
                    (e.path, f'unreadable ({type(exc).__name__}: {exc.strerror or exc})')
                )
        real += subdirs[::-1]  # a stack: popped in name order
    return sorted(files), problems


# ------------------------------------------------------------------------- study selection
#: Tag periods looked for, mm: as :data:`mlv_ros.core.tags.gabor.TAG_PERIOD_RANGE_MM` (the reader
#: does not import the tag package; a test keeps the two equal).
_TAG_PERIOD_MM = (3.0, 16.0)
#: A cine is tagged when its ED image's two strongest spectral peaks (≥ 30° apart, periods within
#: 20 %) each stand this many times above the median of their 9 × 9 bin neighbourhood. Measured
#: on simulated ED images (48²–256², SNR 8 and 20, tagged background): tagged grids 3.5–39 (the
#: low end: 48² long-axis views that are mostly blood pool, hence the second test below),
#: untagged simulations of the same anatomy ≤ 3.7 (≤ 5.0 noise-free), white noise ≤ 3.9. Tags
#: on the myocardium alone (no tagged background) mostly stay below 6: see read_dicom_dir.
_TAG_CLEAR = 6.0
#: A cine of a study with clearly tagged cines is tagged too when, at that study's tag frequency
#: (± 12 %, at least ± 2 spectral bins), two peaks 60–120° apart stand this high (same measure) and
#: this many times above the same test at 0.55 and 1.7 × that frequency. Measured on the same
#: images: tagged ≥ 3.5 and ≥ 1.43 at SNR 20 (2.9 and 1.31 stored in 8 bits), untagged ≤ 3.6
#: and ≤ 1.24.
_TAG_AT_PERIOD = 2.5
_TAG_AT_PERIOD_CONTRAST = 1.25
_RING_TOL = 0.12
_RING_BINS = 2.0
_NULL_RINGS = (0.55, 1.7)
_TAG_MAX_SIDE = 256  # larger images are judged on their central 256 × 256 pixels
_SAME_PLACE_COS = np.cos(np.radians(5.0))
#: A cine with fewer phases than its study is used (each image as the study phase nearest its
#: TriggerTime, the others missing) when every image lies within this fraction of the study's
#: phase interval of its phase: the heart moves little in a quarter of a phase.
_FEWER_PHASES_TOL = 0.25
#: Tags on the heart alone (dark or untagged surroundings) are a small share of the image, so the
#: whole-image spectrum rarely shows them (scores 2–4.5 against the 6 needed). The study then
#: votes (:func:`_window_profiles`, :func:`_study_vote`): each MR cine's first images are cut into
#: windows of :data:`_LOCAL_WINDOW_MM` (at least :data:`_LOCAL_MIN_PX` px, half-overlapping,
#: Hann-tapered) and each spectral bin's power is divided by the image's own background there:
#: the larger of the median power on the same ring (|f|, any angle: isotropic anatomy and
#: noise, of any colour) and the power on the same ray at :data:`_RAY_SCALES` × |f| times the
#: scale squared (a ray: an edge or band, whose power falls off no faster than 1/|f|²; a tag
#: peak stands out of its ray). Over white or coloured noise that ratio is exponential with
#: mean 1 in every bin; the minimum over K images (ED and the next, when it is within
#: :data:`_VOTE_NEXT_FRACTION` of the cycle; tags stay, noise does not) times K is again
#: exponential with mean 1, so the scores of one- and two-image cines share one scale. A cine's
#: profile per tag period (bins :data:`_PERIOD_BINS_MM`, :data:`_VOTE_MIN_PX` px and up) is the
#: largest over its windows of the strongest bin (``line``: one family of tag lines or more) and
#: of the weaker of the best two local maxima 60–120° apart (``grid``); the study's is the median
#: over its cines at one period. Measured (bench ``tag_test.py``, 60 random protocols × 2 noise
#: draws, 8/12/16 bits, SNR 10–40, periods 3.5–10 px, the RV drawn, each against an untagged
#: twin and a bright-blood one): untagged studies grid ≤ 6.29, line ≤ 11.2; heart-only grids
#: grid ≥ 6.75 (median 18.6); one family of lines line ≥ 28.9. Noise alone gives about
#: ln(tests) ≈ 5–9 by chance. The grid threshold is thin (≥ 1.07 ×), so between studies the
#: larger vote in units of its threshold wins (worst tagged-over-untagged ratio of 28,800 pairs
#: 1.12, none lost).
_LOCAL_WINDOW_MM = 60.0
_LOCAL_MIN_PX = 32
_LOCAL_PEAKS = 24
_PERIOD_BINS_MM = np.exp(
    np.arange(np.log(_TAG_PERIOD_MM[0]), np.log(_TAG_PERIOD_MM[1]) + 1e-9, np.log(1.03))
)
_VOTE_MIN_PX = 3.5  # tag periods under 3.5 px are not looked for in windows
_VOTE_MIN_BINS = 5.0  # a period spans at most a fifth of the window (≥ 5 spectral bins)
_RAY_SCALES = (0.5, 0.6, 0.7, 0.8)
_RAY_GAP_BINS = 2.5  # ray samples this far inside the peak (the Hann main lobe is ± 2 bins)
_VOTE_NEXT_FRACTION = 0.2
_TAG_STUDY = 6.5
_TAG_LINES = 16.0
#: One family of tag lines (no intersections to track) when the line score is this many times
#: the grid score: a grid's two families carry the same power (its line score over its grid score
#: 1.2–3.8 measured), one family's partner is noise (5.4 and more).
_SINGLE_LINE_RATIO = 4.5
#: Two single-line series of one slice are a pair when their lines lie this far apart, deg.
_PAIR_MIN_DEG = 30.0
_TAG_STUDY_MIN_CINES = 3
#: A cine of the chosen study that fails the tag test is still used when it was acquired like one
#: of its tagged cines: the same matrix and pixel spacing within this fraction.
_ALIKE_SPACING = 0.02


def _tag_spectrum(image: np.ndarray):
    """
    Return the FFT magnitude of the mean-removed, gently tapered image, and its frequencies.

    The image is cropped to its central 256² at most; frequencies in cycles/px (rows as a column
    vector, columns as a row vector).
    """
    a = np.asarray(image, np.float64)
    h, w = a.shape
    r0, c0 = max(0, (h - _TAG_MAX_SIDE) // 2), max(0, (w - _TAG_MAX_SIDE) // 2)
    a = a[r0:r0 + _TAG_MAX_SIDE, c0:c0 + _TAG_MAX_SIDE]
    h, w = a.shape
    x = (a - a.mean()) * np.outer(np.hanning(h) ** 0.25, np.hanning(w) ** 0.25)
    return np.abs(np.fft.fft2(x)), np.fft.fftfreq(h)[:, None], np.fft.fftfreq(w)[None, :]


def _local_maxima(spec: np.ndarray) -> np.ndarray:
    """Where ``spec`` is positive and not below any of its 8 neighbours (wrapped)."""
    out = spec > 0
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            if dr or dc:
                out &= spec >= np.roll(spec, (dr, dc), axis=(0, 1))
    return out


def _spectral_peaks(
    spec, fr, fc, fmin: float, fmax: float, limit: int = 40, maxima: np.ndarray | None = None
) -> list[tuple[float, float, float]]:
    """
    Return the most prominent local maxima of the half spectrum with ``fmin ≤ |f| ≤ fmax``.

    Local maxima are 3 × 3, wrapped (``maxima`` if already known), returned as ``(prominence,
    angle, |f|)``, most prominent first; prominence = the peak over the median of its 9 × 9
    neighbourhood. Only the ``limit`` highest maxima are measured.
    """
    h, w = spec.shape
    rad = np.hypot(fr, fc)
    band = ((fc > 0) | ((fc == 0) & (fr > 0))) & (rad >= fmin) & (rad <= fmax)
    band &= _local_maxima(spec) if maxima is None else maxima
    rows, cols = np.nonzero(band)
    out = []
    for i in np.argsort(-spec[rows, cols], kind='stable')[:limit]:
        r, c = rows[i], cols[i]
        ref = float(
            np.median(spec[np.ix_((r + np.arange(-4, 5)) % h, (c + np.arange(-4, 5)) % w)])
        )
        out.append(
            (
                float(spec[r, c]) / ref if ref > 0 else np.inf,
                float(np.arctan2(fr[r, 0], fc[0, c])),
                float(rad[r, c]),
            )
        )
    out.sort(key=lambda p: -p[0])
    return out


def _axial_deg(a: float, b: float) -> float:
    """Angle between two wave-vector directions (mod 180°), degrees in 0..90."""
    d = abs(a - b) % math.pi
    return math.degrees(min(d, math.pi - d))


def _tag_grid(image: np.ndarray, pixel_mm: float) -> tuple[float, float, str]:
    """
    Check whether an ED image shows a tag grid.

    ``(score, period_mm, reason)``: the weaker of the two strongest spectral peaks ≥ 30° apart with
    periods within 20 % (see :data:`_TAG_CLEAR`), the stronger one's period, and why the score is 0
    ("" otherwise). A few ms for 256².
    """
    h, w = image.shape
    if min(h, w) < 16:
        return 0.0, np.nan, f'image {h}x{w} too small to show a tag grid'
    if not np.ptp(image) > 0:
        return 0.0, np.nan, 'the ED image is constant'
    lo = max(_TAG_PERIOD_MM[0] / pixel_mm, 2.5)
    hi = min(_TAG_PERIOD_MM[1] / pixel_mm, min(h, w, _TAG_MAX_SIDE) / 3.0)
    if lo >= hi:
        return (
            0.0,
            np.nan,
            f'tag periods of {_TAG_PERIOD_MM[0]:g}–{_TAG_PERIOD_MM[1]:g} mm do not fit its pixels',
        )
    peaks = _spectral_peaks(*_tag_spectrum(image), 1.0 / hi, 1.0 / lo)
    for i, a in enumerate(peaks[:10]):
        for b in peaks[i + 1:]:
            if _axial_deg(a[1], b[1]) >= 30.0 and abs(a[2] / b[2] - 1.0) <= 0.2:
                return min(a[0], b[0]), pixel_mm / a[2], ''
    return 0.0, np.nan, 'no two spectral peaks of one period in the tag band'


def _tag_grid_at(image: np.ndarray, pixel_mm: float, period_mm: float) -> tuple[float, float]:
    """Run the tag-grid test at a known period (:data:`_TAG_AT_PERIOD`): ``(score, contrast)``."""
    spec, fr, fc = _tag_spectrum(image)
    maxima = _local_maxima(spec)
    f0 = pixel_mm / period_mm
    half = max(
        _RING_TOL * f0, _RING_BINS / min(spec.shape)
    )  # the spectrum's bins quantise the period

    def pair(f):  # the best pair 60–120° apart: for each peak, its first such weaker partner
        peaks = _spectral_peaks(spec, fr, fc, f - half, f + half, maxima=maxima)
        return max(
            [
                next(
                    (b[0] for b in peaks[i + 1:] if abs(_axial_deg(a[1], b[1]) - 90.0) <= 30.0),
                    0.0,
                )
                for i, a in enumerate(peaks)
            ],
            default=0.0,
        )

    score, null = pair(f0), max(pair(k * f0) for k in _NULL_RINGS)
    return score, (score / null if null > 0 else (np.inf if score > 0 else 0.0))


def _vote_images(imgs: list) -> list[np.ndarray]:
    """
    Return the images of a cine the study vote looks at: its first, and the next when near it.

    ``imgs`` in time order (``_Image``); the next image is used when it lies within
    :data:`_VOTE_NEXT_FRACTION` of the cycle of the first (by TriggerTime against the cine's
    span, else by its phase count), and has the first one's shape.
    """
    first = imgs[0].pixels
    if len(imgs) < 2 or imgs[1].pixels.shape != first.shape:
        return [first]
    t = np.array([i.trigger_ms for i in imgs], np.float64)
    if np.all(np.isfinite(t)) and t[-1] > t[0]:
        cycle = (t[-1] - t[0]) * len(t) / (len(t) - 1)
        near = t[1] - t[0] <= _VOTE_NEXT_FRACTION * cycle
    else:
        near = 1.0 / max(len(imgs), imgs[0].cardiac_images or 0) <= _VOTE_NEXT_FRACTION
    return [first, imgs[1].pixels] if near else [first]


def _window_profiles(images: list[np.ndarray], pixel_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """
    Return a cine's strongest tag line and tag grid in any window, per tag period.

    See :data:`_TAG_STUDY` for the measure.

    Parameters
    ----------
    images : list of ndarray
        One or two images of one plane, each ``(rows, cols)``, the first defining the shape: ED
        and the image after it (see :func:`_vote_images`).
    pixel_mm : float
        Pixel size, mm.

    Returns
    -------
    line, grid : ndarray, shape ``(len(_PERIOD_BINS_MM),)``
        Per period bin: the largest noise-relative power of one spectral bin (``line``) and the
        weaker of the best pair of local maxima 60–120° apart with periods within the window's
        resolution (``grid``), over the windows; 0 where the period is not looked for.
        Some 20–80 ms for two 256² images.

    """
    line, grid = np.zeros(len(_PERIOD_BINS_MM)), np.zeros(len(_PERIOD_BINS_MM))
    found = _window_ratios(images, pixel_mm)
    if found is None:
        return line, grid
    ratio, wb, near, log_bins = found
    for k in range(len(ratio)):
        line = np.maximum(line, np.max(np.where(near, ratio[k][:, None], 0.0), axis=0))
    return line, _window_grid(ratio, wb, log_bins)


def _window_ratios(images: list[np.ndarray], pixel_mm: float):
    """
    Return the windows' noise-relative spectra of :func:`_window_profiles`, or None.

    ``(ratio (windows, bins), _WindowBins, near (bins, periods): each bin's period bins,
    log of the period bins in pixels)``; None where no window or period is looked at.
    """
    a = np.asarray(images[0], np.float64)
    h, w = a.shape
    win = int(min(max(_LOCAL_MIN_PX, round(_LOCAL_WINDOW_MM / pixel_mm)), h, w))
    lo = max(_TAG_PERIOD_MM[0] / pixel_mm, _VOTE_MIN_PX)
    hi = min(_TAG_PERIOD_MM[1] / pixel_mm, win / _VOTE_MIN_BINS)
    if win < 16 or lo >= hi:
        return None
    step = win // 2
    corners = [(r, c) for r in range(0, h - win + 1, step) for c in range(0, w - win + 1, step)]
    stacks = [
        np.array([np.asarray(im, np.float64)[r:r + win, c:c + win] for r, c in corners])
        for im in images
    ]
    keep = np.ptp(stacks[0], axis=(1, 2)) > 0
    stacks = [s[keep] for s in stacks]
    if not keep.any():
        return None
    wb = _WindowBins(win, lo, hi)
    ratio = _window_ratio(stacks, wb)
    fa = wb.rad[wb.bins]
    log_bins = np.log(_PERIOD_BINS_MM / pixel_mm)
    tol = 0.5 / (win * fa) + 0.04
    near = np.abs(log_bins[None, :] + np.log(fa)[:, None]) <= tol[:, None]  # (bins, periods)
    return ratio, wb, near, log_bins


class _WindowBins:
    """
    The spectral bins of a window looked at for tags, and the samples of their background.

    Parameters
    ----------
    win : int
        Window size, pixels.
    lo, hi : float
        Tag periods looked for, pixels.

    """

    def __init__(self, win: int, lo: float, hi: float):
        self.win = win
        f = np.fft.fftfreq(win)
        fr, fc = np.repeat(f[:, None], win, 1).ravel(), np.repeat(f[None, :], win, 0).ravel()
        self.rad, self.ang = np.hypot(fr, fc), np.arctan2(fr, fc)
        rad = self.rad
        half = (fc > 0) | ((fc == 0) & (fr > 0))
        bins = np.flatnonzero(half & (rad >= 1.0 / hi) & (rad <= 1.0 / lo))
        self.bins = bins
        self.ring = np.rint(rad * win).astype(int)
        self.rings = [np.flatnonzero(half & (self.ring == k)) for k in range(win // 2 + 1)]
        off = np.arange(-1, 2)
        self.rays = []  # (scale, 3 × 3 patch indices around s·f) per bin
        for s in _RAY_SCALES:
            if s != _RAY_SCALES[0]:
                use = rad[bins] * win * (1.0 - s) >= _RAY_GAP_BINS - 1e-6
            else:
                use = np.ones(len(bins), bool)  # the innermost sample always
            r0 = np.rint(fr[bins] * s * win).astype(int)
            c0 = np.rint(fc[bins] * s * win).astype(int)
            idx = ((r0[:, None, None] + off[None, :, None]) % win) * win + (
                (c0[:, None, None] + off[None, None, :]) % win
            )
            self.rays.append((s, idx.reshape(len(bins), -1), use))


def _window_ratio(stacks: list[np.ndarray], wb: _WindowBins) -> np.ndarray:
    """
    Return each window's noise-relative power per bin, the weaker over the images, × images.

    ``stacks``: per image, its windows ``(n, win, win)``; the result is ``(n, len(wb.bins))``.
    """
    win, bins, n = wb.win, wb.bins, len(stacks[0])
    taper = np.outer(np.hanning(win), np.hanning(win))
    ratio = None
    for s in stacks:
        p = np.abs(np.fft.fft2((s - s.mean(axis=(1, 2), keepdims=True)) * taper)) ** 2
        p = p.reshape(n, -1)
        ring_bg = np.zeros((n, win // 2 + 1))
        for k, idx in enumerate(wb.rings):
            if len(idx):  # exponential power: its median is ln 2 × its mean
                ring_bg[:, k] = np.median(p[:, idx], axis=1) / math.log(2.0)
        bg = ring_bg[:, wb.ring[bins]]
        for sc, idx, use in wb.rays:
            bg = np.maximum(bg, np.where(use, p[:, idx].mean(axis=2) * sc**2, 0.0))
        r = p[:, bins] / np.maximum(bg, np.finfo(np.float64).tiny)
        ratio = r if ratio is None else np.minimum(ratio, r)
    ratio *= len(stacks)
    return ratio


def _window_grid(ratio: np.ndarray, wb: _WindowBins, log_bins: np.ndarray) -> np.ndarray:
    """
    Return per period bin the best grid any window shows (see :func:`_window_profiles`).

    A grid: the weaker of a pair of local maxima of the window's ratio map 60–120° apart, with
    periods within the window's resolution. ``log_bins``: log of the period bins in pixels.
    """
    win, bins, n = wb.win, wb.bins, len(ratio)
    fa, th = wb.rad[bins], wb.ang[bins]
    grid = np.zeros(len(log_bins))
    # local maxima of each window's ratio map (both half planes, wrapped)
    full = np.zeros((n, win * win))
    full[:, bins] = ratio
    full = full.reshape(n, win, win)
    mirror = (-np.arange(win)) % win
    full = full + full[:, mirror][:, :, mirror]
    peak = full > 0
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            if dr or dc:
                peak &= full >= np.roll(full, (dr, dc), axis=(1, 2))
    peak = peak.reshape(n, -1)[:, bins]
    for k in range(n):
        cand = np.flatnonzero(peak[k])
        top = cand[np.argsort(-ratio[k][cand], kind='stable')[:_LOCAL_PEAKS]]
        if len(top) < 2:
            continue
        fk, tk, rk = fa[top], th[top], ratio[k][top]
        d = np.abs(tk[:, None] - tk[None, :]) % np.pi
        apart = np.abs(np.degrees(np.minimum(d, np.pi - d)) - 90.0) <= 30.0
        fm = 0.5 * (fk[:, None] + fk[None, :])
        tl = 0.5 / (win * fm) + 0.04
        ok = apart & (np.abs(np.log(fk[:, None] / fk[None, :])) <= 2.0 * tl)
        i, j = np.nonzero(np.triu(ok, 1))
        if not len(i):
            continue
        score = np.minimum(rk[i], rk[j])
        hit = np.abs(log_bins[None, :] + np.log(fm[i, j])[:, None]) <= tl[i, j][:, None]
        grid = np.maximum(grid, np.max(np.where(hit, score[:, None], 0.0), axis=0))
    return grid


@dataclass
class _Vote:
    """A group of cines' study vote (see :data:`_TAG_STUDY`)."""

    grid: float  # the median grid score at its best period
    grid_period_mm: float
    line: float  # the median line score at its best period
    line_period_mm: float
    each_grid: np.ndarray  # each cine's grid score at grid_period_mm
    each_line: np.ndarray  # each cine's line score at line_period_mm

    @property
    def score(self) -> float:
        """Return the vote in units of its threshold: the larger of grid and line (≥ 1: tagged)."""
        return max(self.grid / _TAG_STUDY, self.line / _TAG_LINES)

    @property
    def single_line(self) -> bool:
        """Check for one family of tag lines: the line passes, the grid is far weaker."""
        return self.line >= _TAG_LINES and self.line >= _SINGLE_LINE_RATIO * self.grid

    @property
    def by_line(self) -> bool:
        """Check whether the line vote decides (tag lines, or lines above the grid)."""
        return self.single_line or self.line / _TAG_LINES > self.grid / _TAG_STUDY

    @property
    def period_mm(self) -> float:
        """
        Return the tag period, mm: the strongest family's.

        A grid's best pair can be its diagonal harmonic (λ/√2, the two 45° components of a
        sin²·sin² grid); its strongest single family is the fundamental.
        """
        return self.line_period_mm

    def each(self) -> np.ndarray:
        """Return each cine's score at the deciding period, in units of its threshold."""
        return self.each_line / _TAG_LINES if self.by_line else self.each_grid / _TAG_STUDY


def _plateau_centre(v: np.ndarray) -> int:
    """
    Return the index of the largest value of ``v``, the middle one of a run of equal maxima.

    One spectral bin spans several period bins (the window's resolution): the run's middle is
    its period, where the first would be its shortest.
    """
    k = int(np.argmax(v))
    end = k
    while end + 1 < len(v) and v[end + 1] == v[k]:
        end += 1
    return (k + end) // 2


def _study_vote(cines: list[tuple[list[np.ndarray], float]]) -> _Vote:
    """
    Return the tag grid or tag lines a group of cines shares (tags on the heart alone).

    Parameters
    ----------
    cines : list of (images, pixel_mm)
        Each cine's vote images (:func:`_vote_images`) and pixel size, mm.

    Returns
    -------
    _Vote
        The median over the cines of :func:`_window_profiles` at the best period, grid and line.

    """
    profs = [_window_profiles(ims, px) for ims, px in cines]
    line = np.array([p[0] for p in profs])
    grid = np.array([p[1] for p in profs])
    ml, mg = np.median(line, axis=0), np.median(grid, axis=0)
    kl, kg = _plateau_centre(ml), _plateau_centre(mg)
    return _Vote(
        float(mg[kg]),
        float(_PERIOD_BINS_MM[kg]),
        float(ml[kl]),
        float(_PERIOD_BINS_MM[kl]),
        grid[:, kg],
        line[:, kl],
    )


@dataclass
class _Cine:
    """One plane of one series (its images in time order), as the study selection sees it."""

    imgs: list[_Image]
    kind: str = ''  # why it is not an MR cine ("" when it is)
    tag: float = 0.0  # _tag_grid score of its ED image
    period_mm: float = np.nan
    tag_reason: str = ''
    tagged: bool = False
    why: str = ''  # why it is not used ("" when it is)
    # Phase plan of a used cine: the images used, their phase indices and the phase count.
    use: list[_Image] = field(default_factory=list)
    phases: list[int] = field(default_factory=list)
    num_phases: int = 0
    # The second single-line series of this slice, its lines crossing this one's (or None).
    partner: '_Cine | None' = None

    @property
    def first(self) -> _Image:
        return self.imgs[0]

    @property
    def group(self) -> tuple[str, str]:
        return self.first.study_uid, self.first.frame_of_reference_uid

    @property
    def mosaic(self) -> str:
        return next((i.mosaic for i in self.imgs if i.mosaic), '')

    @property
    def acquired(self) -> tuple[bool, float] | None:
        times = [i.acquired for i in self.imgs if i.acquired is not None]
        return min(times) if times and len({t[0] for t in times}) == 1 else None

    def describe(self) -> str:
        f = self.first
        desc = f' {f.description!r}' if f.description else ''
        return (
            f'series {f.series_uid or "(no SeriesInstanceUID)"}{desc} (SeriesNumber '
            f'{f.series_number}, '
            f'{len(self.imgs)} image(s))'
        )


def _cine_kind(c: _Cine) -> str:
    """Why a plane's images are not an MR cine ("" when they are)."""
    f = c.first
    if f.modality and f.modality != 'MR':
        return f'modality {f.modality}, not MR'
    if c.mosaic:
        rows, cols = f.pixels.shape
        return (
            f'Siemens MOSAIC ({c.mosaic}): several slices tiled in each {rows}x{cols} image, '
            'not a cine of '
            f'one slice (export the series as single-slice images)'
        )
    if len(c.imgs) == 1:  # one image of a longer cine is a cine missing phases
        return '' if (f.cardiac_images or 0) > 1 else 'one frame, not a cine'
    trig = [i.trigger_ms for i in c.imgs]
    if all(np.isfinite(trig)) and len(set(np.round(trig, 3))) == 1:
        return f'not a cine: its {len(c.imgs)} images share one TriggerTime ({trig[0]:g} ms)'
    if not any(np.isfinite(trig)) and not any((i.cardiac_images or 0) > 1 for i in c.imgs):
        return (
            f'not a cine: {len(c.imgs)} images at one position without TriggerTime or '
            'CardiacNumberOfImages'
        )
    return ''


def _later(a: _Cine, b: _Cine) -> bool | None:
    """
    Check whether ``a`` was acquired after ``b``.

    By acquisition/series time where both have one and they differ, else by SeriesNumber; None when
    nothing tells.
    """
    ta, tb = a.acquired, b.acquired
    if ta is not None and tb is not None and ta[0] == tb[0] and ta[1] != tb[1]:
        return ta[1] > tb[1]
    if a.first.series_number != b.first.series_number:
        return a.first.series_number > b.first.series_number
    return None


def _same_place(a: _Cine, b: _Cine) -> bool:
    """Check for the same slice location: parallel planes (5°) less than half a slab apart."""
    ga, gb = a.first.geometry, b.first.geometry
    cos = float(ga.normal @ gb.normal)
    if abs(cos) < _SAME_PLACE_COS:
        return False
    gap = abs(float((ga.image_position - gb.image_position) @ ga.normal))
    return gap < 0.5 * min(ga.slice_thickness, gb.slice_thickness)


def _match_phases(ref: np.ndarray, t: np.ndarray) -> list[int]:
    """
    Match each ``ref`` entry to one index into ``t``, minimising the summed |ref − t|.

    ``t`` is sorted with ``len(t) ≥ len(ref)``; the indices are strictly increasing (dynamic
    programming).
    """
    n, m = len(ref), len(t)
    cost = np.abs(ref[:, None] - t[None, :])
    total = np.full((n, m), np.inf)
    total[0] = cost[0]
    arg = np.zeros((n, m), dtype=np.int64)
    for k in range(1, n):
        prev, best = total[k - 1], 0
        for j in range(1, m):  # best predecessor among 0 .. j-1
            if prev[j - 1] < prev[best]:
                best = j - 1
            total[k, j] = cost[k, j] + prev[best]
            arg[k, j] = best
    j = int(np.argmin(total[-1]))
    out = [j]
    for k in range(n - 1, 0, -1):
        j = int(arg[k, j])
        out.append(j)
    return out[::-1]


@dataclass
class _Selection:
    cines: list[_Cine]  # used, each with its phase plan
    study_uid: str
    studies: dict[str, int]
    choice: str
    problems: list[tuple[str, str]]
    warnings: list[tuple[str, str]]
    left_out: list[tuple[str, str]]
    tag_lines: int = TAGS_GRID  # TAGS_LINES: a single-line study (pairs are the cines' partner)


def _plan_phases(c: _Cine, warned: list, left_out: list | None) -> None:
    """Use a cine as it is: phase indices from its images (a gap keeps the later indices)."""
    phases, num, gap = _phase_indices(c.imgs)
    c.use, c.phases, c.num_phases = c.imgs, phases, num
    if gap:
        warned.append(
            (c.first.path, f'series {c.first.series_uid or "(no SeriesInstanceUID)"}: {gap}')
        )
        if left_out is not None:
            left_out.append((c.first.path, f'{c.describe()}: {gap}'))


def _match_study_phases(used: list[_Cine], warned: list, left_out: list) -> None:
    """
    Give every used cine the study's phase count N (the most common; of a tie the smallest).

    A cine with more phases gets the N images nearest the study's trigger times (each phase's
    median over the N-phase cines; phase fractions where a time is missing); one with fewer phases
    gives each image the study phase nearest its trigger time when every image lies within
    :data:`_FEWER_PHASES_TOL` of a phase interval of one (distinct phases; the others are missing,
    so it is listed in ``left_out``), otherwise it is left out (``why``).
    """
    if not used:
        return
    plans = {id(c): _phase_indices(c.imgs) for c in used}
    counts = Counter(plans[id(c)][1] for c in used)
    top = max(counts.values())
    n = min(k for k, v in counts.items() if v == top)
    ref = np.full(n, np.nan)
    for k in range(n):
        times = [
            img.trigger_ms
            for c in used
            if plans[id(c)][1] == n
            for img, ph in zip(c.imgs, plans[id(c)][0])
            if ph == k and np.isfinite(img.trigger_ms)
        ]
        if times:
            ref[k] = float(np.median(times))
    for c in used:
        phases, num, gap = plans[id(c)]
        if num == n:
            _plan_phases(c, warned, left_out)
        elif num < n or len(c.imgs) < n:
            _fit_fewer_phases(c, num, ref, left_out)
        else:
            _fit_more_phases(c, phases, num, ref, warned)


def _fit_fewer_phases(c: _Cine, num: int, ref: np.ndarray, left_out: list) -> None:
    """
    Place each image of a cine of ``num`` phases at the nearest of the study's, or leave it out.

    Parameters
    ----------
    c : _Cine
        The cine; its ``use``/``phases``/``num_phases`` are set, or ``why`` says why not.
    num : int
        Its phase count.
    ref : np.ndarray
        The study's trigger time of each phase (ms, NaN where unknown), shape (N,).
    left_out : list
        ``(path, reason)`` appended either way (the study misses phases of this slice).

    """
    n = len(ref)
    t = np.array([i.trigger_ms for i in c.imgs])
    step = float(np.median(np.diff(ref))) if n > 1 and np.all(np.isfinite(ref)) else np.nan
    if np.all(np.isfinite(t)) and np.isfinite(step) and step > 0 and len(t) <= n:
        pick = _match_phases(t, ref)  # a distinct study phase for each image
        off = float(np.max(np.abs(ref[pick] - t)))
        if off <= _FEWER_PHASES_TOL * step:
            c.use, c.phases, c.num_phases = list(c.imgs), list(pick), n
            missing = sorted(set(range(n)) - set(pick))
            left_out.append(
                (
                    c.first.path,
                    (
                        f'{c.describe()}: {num} phase(s) in a study of {n}: each image '
                        'used as the study phase '
                        f'nearest its TriggerTime (largest difference {off:.0f} ms, '
                        f'{_FEWER_PHASES_TOL:g} of the '
                        f'{step:.0f} ms phase interval allowed); phase(s) '
                        f'{", ".join(str(k + 1) for k in missing)} '
                        f'of {n} missing'
                    ),
                )
            )
            return
        far = (
            f"; its TriggerTimes lie up to {off:.0f} ms from the study's "
            f'({_FEWER_PHASES_TOL:g} of the '
            f'{step:.0f} ms phase interval allowed)'
        )
    else:
        far = (
            '; TriggerTimes missing'
            if not np.all(np.isfinite(t)) or not np.isfinite(step)
            else ''
        )
    c.why = (
        f'{num} phase(s) ({len(c.imgs)} image(s)) where the study has {n}: too few to '
        'give every '
        f"phase, and not matched to the study's phases by TriggerTime{far}"
    )
    left_out.append((c.first.path, f'{c.describe()} not used: {c.why}'))


def _fit_more_phases(c: _Cine, phases: list[int], num: int, ref: np.ndarray, warned) -> None:
    """
    Use the images of a cine of ``num`` phases nearest the study's N trigger times.

    Parameters
    ----------
    c : _Cine
        The cine; its ``use``/``phases``/``num_phases`` are set.
    phases : list of int
        Its images' own phase indices.
    num : int
        Its phase count.
    ref : np.ndarray
        The study's trigger time of each phase (ms, NaN where unknown), shape (N,); phase
        fractions stand in where a time is missing.
    warned : list
        ``(path, warning)`` appended: the images not used.

    """
    n = len(ref)
    t = np.array([i.trigger_ms for i in c.imgs])
    timed = bool(np.all(np.isfinite(ref)) and np.all(np.isfinite(t)))
    r, tt = (ref, t) if timed else (np.arange(n) / n, np.asarray(phases, np.float64) / num)
    pick = _match_phases(r, tt)
    c.use, c.phases, c.num_phases = [c.imgs[j] for j in pick], list(range(n)), n
    off = float(np.max(np.abs(r - tt[pick])))
    how = (
        f'largest difference {off:.0f} ms'
        if timed
        else f'by phase fraction (TriggerTime missing), largest difference {off:.2f} '
        'of the cycle'
    )
    warned.append(
        (
            c.first.path,
            f"{c.describe()}: {num} phases in a study of {n}: the {n} nearest the study's "
            f'trigger times used ({how}), {len(c.imgs) - n} image(s) not used',
        )
    )


def _pixel_mm(c: _Cine) -> float:
    g = c.first.geometry
    return 0.5 * (g.row_spacing + g.column_spacing)


def _acquired_alike(c: _Cine, tagged: list[_Cine]) -> _Cine | None:
    """
    Return the tagged cine that ``c`` was acquired like, or None.

    Alike: same matrix, pixel spacing within :data:`_ALIKE_SPACING`.
    """
    g = c.first.geometry
    for t in tagged:
        h = t.first.geometry
        if (
            c.first.pixels.shape == t.first.pixels.shape
            and abs(g.row_spacing / h.row_spacing - 1.0) <= _ALIKE_SPACING
            and abs(g.column_spacing / h.column_spacing - 1.0) <= _ALIKE_SPACING
        ):
            return t
    return None


def _select_study(cines: list[_Cine], study: str | None, root, problems: list) -> _Selection:
    """Choose the study, and the cines of it to use (see :func:`read_dicom_dir`)."""
    _test_tags(cines)
    groups: dict[tuple[str, str], list[_Cine]] = defaultdict(list)
    for c in cines:
        groups[c.group].append(c)
    heart = _heart_votes(groups)
    tally: Counter = Counter()
    for c in cines:
        tally[c.first.study_uid] += int(c.tagged)
    studies = dict(sorted(tally.items(), key=lambda kv: (-kv[1], kv[0])))
    best, pool = _pick_group(groups, heart, study, studies, root, problems)
    n_tagged = sum(c.tagged for c in groups[best])
    n_cines = sum(not c.kind for c in groups[best])
    others = [
        f'{_study_name(u)} ({n} tagged cine(s))' for u, n in studies.items() if u != best[0]
    ]
    also = f'; also under the folder: study {", study ".join(others)}' if others else ''
    how = ' (asked for)' if study else ''
    if not n_tagged and not n_cines:
        return _select_every_image(cines, pool, study, best[0], studies, also)
    period = (
        float(np.nanmedian([c.period_mm for c in groups[best] if c.tagged]))
        if n_tagged
        else np.nan
    )
    vote = heart.get(best)
    on_heart = vote is not None and n_tagged > 0  # tagged on the heart alone: the votes decided
    single_line = on_heart and vote.single_line
    warned: list[tuple[str, str]] = []
    left_out: list[tuple[str, str]] = []
    used = _mark_unused(cines, best, n_tagged, period, on_heart, left_out)
    if n_tagged:
        _judge_untagged(used, warned)
        used = [c for c in used if not c.why]
    partners = _pair_line_series(used, vote.period_mm) if single_line else []
    used = [c for c in used if c not in partners]
    _keep_latest(used, warned)
    used = [c for c in used if not c.why]
    _match_study_phases(used + partners, warned, left_out)
    for c in used:
        if c.partner is not None and c.partner.why:  # the second series' phases did not fit
            warned.append((c.partner.first.path, f'{c.partner.describe()} not paired: '
                           f'{c.partner.why}'))
            c.partner = None
    used = [c for c in used if not c.why]
    choice = _choice_text(
        f'study {_study_name(best[0])}{how}', also, n_tagged, n_cines, period, vote
    )
    if single_line:
        pairs = sum(c.partner is not None for c in used)
        choice += (
            f'; single-line tags (one family of lines a cine): {pairs} of {len(used)} slice(s) '
            'paired with a second single-line series whose lines cross theirs (both directions '
            'measured), the others measure motion across their lines only'
        )
    tag_lines = TAGS_LINES if single_line else TAGS_GRID
    return _Selection(
        used, best[0], studies, choice, _series_problems(cines), warned, left_out, tag_lines
    )


def _pair_line_series(used: list[_Cine], period_mm: float) -> list[_Cine]:
    """
    Pair the two single-line series of a slice whose lines cross; return the second of each pair.

    Vendors acquire single-line tags of one slice twice, in separate breath-holds, with the lines
    turned between them. Two cines of different series at one slice location (:func:`_same_place`,
    same matrix) are a pair when their ED images show different families of lines
    (:func:`_crossing_lines`). The earlier series (:func:`_later`, else the smaller
    SeriesInstanceUID) keeps the slice and takes the other as ``partner``. Two series of one
    family are a repeated acquisition (:func:`_keep_latest`).
    """
    partners: list[_Cine] = []
    for i, a in enumerate(used):
        if a.partner is not None or a in partners:
            continue
        for b in used[i + 1:]:
            if (
                b in partners
                or b.partner is not None
                or b.first.series_uid == a.first.series_uid
                or b.first.pixels.shape != a.first.pixels.shape
                or not _same_place(a, b)
            ):
                continue
            if _crossing_lines(a, b, period_mm):
                first, second = (b, a) if _later(a, b) or (
                    _later(a, b) is None and b.first.series_uid < a.first.series_uid
                ) else (a, b)
                first.partner = second
                partners.append(second)
                break
    return partners


def _crossing_lines(a: _Cine, b: _Cine, period_mm: float) -> bool:
    """
    Check whether two single-line cines of one slice show families of lines 30° or more apart.

    Each cine's line direction is that of its strongest spectral bin at the study's period in
    the study vote's windows (:func:`_line_direction`); 30° is the separation the tag grid's
    spectral estimate asks of two directions (``mlv_ros.core.tags.gabor``).
    """
    da, db = _line_direction(a, period_mm), _line_direction(b, period_mm)
    if da is None or db is None:
        return False
    return _axial_deg(da, db) >= _PAIR_MIN_DEG


def _line_direction(c: _Cine, period_mm: float) -> float | None:
    """
    Return the wave-vector angle (rad) of a cine's strongest line at ``period_mm``, or None.

    The strongest noise-relative bin (:func:`_window_ratios` of its vote images) whose period
    bin is within 3 % of ``period_mm``; None unless it passes :data:`_TAG_LINES`.
    """
    found = _window_ratios(_vote_images(c.imgs), _pixel_mm(c))
    if found is None:
        return None
    ratio, wb, near, log_bins = found
    k = int(np.argmin(np.abs(log_bins - np.log(period_mm / _pixel_mm(c)))))
    cols = near[:, max(k - 1, 0):k + 2].any(axis=1)  # the period's bin and its neighbours
    if not cols.any():
        return None
    r = np.where(cols[None, :], ratio, 0.0)
    w, j = np.unravel_index(int(np.argmax(r)), r.shape)
    if r[w, j] < _TAG_LINES:
        return None
    return float(wb.ang[wb.bins[j]])


def _study_name(uid: str) -> str:
    """Name a study in messages, also one without a StudyInstanceUID."""
    return uid or '(no StudyInstanceUID)'


def _test_tags(cines: list[_Cine]) -> None:
    """Say what each cine is (``kind``), and whether an MR cine's ED image shows a tag grid."""
    for c in cines:
        c.kind = _cine_kind(c)
        if not c.kind:
            c.tag, c.period_mm, c.tag_reason = _tag_grid(c.first.pixels, _pixel_mm(c))
            c.tagged = c.tag >= _TAG_CLEAR


def _heart_votes(groups: dict[tuple[str, str], list[_Cine]]) -> dict[tuple[str, str], _Vote]:
    """
    Let each group without a clearly tagged cine vote on a grid its cines share in windows.

    Tags on the heart alone are too small a part of each image for its spectrum; a passing vote
    marks the cines that carry the grid (``tagged``, ``period_mm``) and says why the others fail.
    Returns the votes by group.
    """
    heart: dict[tuple[str, str], _Vote] = {}
    for key, cs in groups.items():
        mr = [c for c in cs if not c.kind]
        if len(mr) >= _TAG_STUDY_MIN_CINES and not any(c.tagged for c in mr):
            vote = _study_vote([(_vote_images(c.imgs), _pixel_mm(c)) for c in mr])
            heart[key] = vote
            if vote.score >= 1.0:
                what = 'tag lines' if vote.single_line else 'a tag grid'
                for c, v in zip(mr, vote.each()):
                    c.tagged, c.period_mm = bool(v >= 1.0), vote.period_mm
                    if not c.tagged:
                        c.tag_reason = (
                            f'{c.tag_reason or "no clear grid in the whole image"}; in windows of '
                            f"{_LOCAL_WINDOW_MM:g} mm {what} of the study's "
                            f'{vote.period_mm:.1f} mm period stand(s) {v:.2f} of the needed '
                            "height above the image's own spectral background"
                        )
    return heart


def _rank(cs: list[_Cine], vote: _Vote | None) -> tuple:
    """
    Rank a group of cines as a candidate study: the larger, the better.

    By clearly tagged cines, then a passing grid vote, then the vote (tags on the heart alone
    beat untagged), then the number of MR cines and of images.
    """
    return (
        sum(c.tag >= _TAG_CLEAR for c in cs),
        vote is not None and vote.score >= 1.0 and not vote.single_line,
        vote.score if vote is not None else 0.0,
        sum(not c.kind for c in cs),
        sum(len(c.imgs) for c in cs),
    )


def _pick_group(groups, heart, study, studies, root, problems) -> tuple[tuple[str, str], list]:
    """
    Take the best-ranked group (:func:`_rank`) of the study asked for, if one is.

    Parameters
    ----------
    groups : dict
        Cines by (StudyInstanceUID, FrameOfReferenceUID).
    heart : dict
        Grid votes by group (:func:`_heart_votes`).
    study : str or None
        The StudyInstanceUID asked for.
    studies : dict
        Tagged cines by StudyInstanceUID, most first (for the message).
    root : Path
        The folder read (for the message).
    problems : list
        Carried by the error.

    Returns
    -------
    best : (str, str)
        The group taken.
    pool : list of (str, str)
        The groups it was taken from, sorted.

    Raises
    ------
    DicomReadError
        ``study`` is not under ``root``.

    """
    pool = sorted(groups)  # of equal ranks, max() keeps the first: the smaller UIDs
    if study:
        pool = [k for k in pool if k[0] == study]
        if not pool:
            there = ', '.join(f'{_study_name(u)} ({n} tagged cine(s))' for u, n in studies.items())
            raise DicomReadError(
                f'study {study} is not under {root}; the studies there: {there}: '
                f'ask for one of these',
                problems,
            )
    return max(pool, key=lambda k: _rank(groups[k], heart.get(k))), pool


def _select_every_image(cines, pool, study, best_uid, studies, also) -> _Selection:
    """
    Select every image (of the study asked for) as it is: without an MR cine, none to choose by.

    Single images and other modalities load for downstream to say what they are; Siemens MOSAIC
    images never do.

    Parameters
    ----------
    cines : list of _Cine
        Every cine read.
    pool : list of (str, str)
        The groups of the study asked for (else all).
    study : str or None
        The StudyInstanceUID asked for.
    best_uid : str
        The StudyInstanceUID of the best-ranked group.
    studies : dict
        Tagged cines by StudyInstanceUID.
    also : str
        The other studies under the folder, for the message.

    Returns
    -------
    _Selection

    """
    warned: list[tuple[str, str]] = []
    used = [c for c in cines if c.group in pool and not c.mosaic]
    for c in cines:
        if c.group not in pool:
            c.why = f'another study (StudyInstanceUID {_study_name(c.first.study_uid)})'
        elif c.mosaic:
            c.why = c.kind
    for c in used:
        _plan_phases(c, warned, None)
    what = f'study {study}' if study else 'the folder'
    return _Selection(
        used,
        best_uid if study else '',
        studies,
        f'no MR cine in {what}: every image loaded as it is{also if study else ""}',
        _series_problems(cines),
        warned,
        [],
    )


def _mark_unused(cines, best, n_tagged, period, on_heart, left_out) -> list[_Cine]:
    """
    Mark why each cine outside the chosen group, or not a tagged MR cine, is not used.

    Parameters
    ----------
    cines : list of _Cine
        Every cine read; ``why`` is set on those not used.
    best : (str, str)
        The chosen (StudyInstanceUID, FrameOfReferenceUID).
    n_tagged : int
        Tagged cines of the chosen group.
    period : float
        The study's tag period (mm; NaN without a tagged cine).
    on_heart : bool
        The study is tagged on the heart alone (its cines voted; no second test).
    left_out : list
        ``(path, reason)`` appended for MR cines of the chosen study in another frame of
        reference.

    Returns
    -------
    list of _Cine
        The cines still to be used.

    """
    used = []
    for c in cines:
        why = [c.kind] if c.kind else []
        if c.group != best:
            if c.first.study_uid != best[0]:
                why.append(f'another study (StudyInstanceUID {_study_name(c.first.study_uid)})')
            else:
                why.append(
                    f'another frame of reference of the chosen study (FrameOfReferenceUID '
                    f'{c.first.frame_of_reference_uid or "(none)"}, chosen {best[1] or "(none)"})'
                )
                if not c.kind and (c.tagged or not n_tagged):
                    left_out.append((c.first.path, f'{c.describe()} not used: {why[-1]}'))
        elif not c.kind and n_tagged and not c.tagged and not on_heart:
            _test_at_period(c, period)
        if why:
            c.why = '; '.join(why)
        else:
            used.append(c)
    return used


def _test_at_period(c: _Cine, period: float) -> None:
    """Test again at the study's tag period (mm) a cine whose own strongest grid is unclear."""
    score, contrast = _tag_grid_at(c.first.pixels, _pixel_mm(c), period)
    c.tagged = score >= _TAG_AT_PERIOD and contrast >= _TAG_AT_PERIOD_CONTRAST
    if not c.tagged:
        c.tag_reason = (
            c.tag_reason
            or f'its strongest grid stands {c.tag:.1f}x above its surroundings, '
            f'{_TAG_CLEAR:g} needed'
        ) + (
            f"; at the study's tag period ({period:.1f} mm) {score:.1f}x, "
            f'{contrast:.2f}x the neighbouring '
            f'frequencies ({_TAG_AT_PERIOD:g} and {_TAG_AT_PERIOD_CONTRAST:g} needed)'
        )


def _choice_text(which_study, also, n_tagged, n_cines, period, vote) -> str:
    """
    Say which study was taken and why (:attr:`DicomReadResult.choice`).

    Parameters
    ----------
    which_study : str
        ``study <UID>``, with `` (asked for)`` where it was.
    also : str
        The other studies under the folder.
    n_tagged, n_cines : int
        Tagged cines and MR cines of the chosen group.
    period : float
        The study's tag period (mm).
    vote : _Vote or None
        The chosen group's grid vote, where it voted.

    Returns
    -------
    str

    """
    if n_tagged and vote is not None:
        what = f'{period:.1f} mm tag lines' if vote.single_line else f'a {period:.1f} mm grid'
        return (
            f'{which_study}: {n_tagged} tagged cine(s), tags on the heart alone '
            f'(its cines share {what} in windows of their first images: '
            f'{vote.score:.1f}x the threshold){also}'
        )
    if n_tagged:
        return f'{which_study}: {n_tagged} tagged cine(s){also}'
    if vote is not None:
        which = (
            'the study whose cines come closest to sharing a tag grid in windows '
            f'({vote.score:.2f}x the threshold) taken, its {n_cines} MR cine(s) all '
            'used'
        )
    else:
        which = f'the study with the most MR cines ({n_cines}) taken, all of them used'
    return (
        f"{which_study}: no cine shows a tag grid in its ED image's spectrum, "
        'nor do its '
        f'cines share one in windows; {which}{also}'
    )


def _judge_untagged(used: list[_Cine], warned: list) -> None:
    """
    Return the chosen study's MR cines whose ED image fails the tag test.

    At the slice of a tagged cine, not used (the tagged one is); of a constant image or acquired
    unlike every tagged cine (matrix, pixel size), not used; otherwise used with a warning (thin
    margins on small or mostly blood-pool views must not cost a slice).
    """
    tagged = [c for c in used if c.tagged]
    for c in used:
        if c.tagged:
            continue
        at = next((t for t in tagged if _same_place(t, c)), None)
        alike = _acquired_alike(c, tagged)
        if not np.ptp(c.first.pixels) > 0:
            c.why = f'not tagged: {c.tag_reason}'
        elif at is not None:
            c.why = (
                f'not tagged ({c.tag_reason}); the tagged {at.describe()} at this slice '
                'position is used'
            )
        elif alike is None:
            rows, cols = c.first.pixels.shape
            g = c.first.geometry
            c.why = (
                f"not tagged ({c.tag_reason}); and acquired unlike the study's tagged cines "
                f'({rows}x{cols} '
                f'pixels of {g.row_spacing:.3g} x {g.column_spacing:.3g} mm)'
            )
        else:
            warned.append(
                (
                    c.first.path,
                    f'{c.describe()}: its ED image shows no clear tag grid ({c.tag_reason}); '
                    f'used, being of the chosen study and acquired like its tagged '
                    f'{alike.describe()} (if it is not a tagged cine, leave it out of '
                    f'the folder)',
                )
            )


def _keep_latest(used: list[_Cine], warned: list) -> None:
    """
    Keep the latest of cines of different series at one slice location (:func:`_later`).

    The others are marked (``why``). Where nothing tells which is later, the one with the most
    images (then the first by SeriesInstanceUID) is kept, with a warning saying so (never both: a
    slice twice in the stack).
    """
    places: list[list[_Cine]] = []
    for c in used:
        for p in places:
            if _same_place(p[0], c):
                p.append(c)
                break
        else:
            places.append([c])
    for p in places:
        if len({c.first.series_uid for c in p}) < 2:
            continue
        latest = next(
            (
                c
                for c in p
                if all(o.first.series_uid == c.first.series_uid or _later(c, o) for o in p)
            ),
            None,
        )
        how = 'the later'
        if latest is None:  # nothing tells (or a tie): one, independent of the file order
            latest = min(p, key=lambda c: (-len(c.imgs), c.first.series_uid, c.first.path))
            how = (
                '(no acquisition time or SeriesNumber tells which is later) the one with the '
                'most images '
                '(then the first by SeriesInstanceUID),'
            )
        earlier = [o for o in p if o.first.series_uid != latest.first.series_uid]
        for o in earlier:
            o.why = f'repeated acquisition of a slice: {how} {latest.describe()} used'
        warned.append(
            (
                latest.first.path,
                f'slice acquired more than once: {how} {latest.describe()} used, '
                f'not {"; ".join(o.describe() for o in earlier)}',
            )
        )


def _series_problems(cines: list[_Cine]) -> list[tuple[str, str]]:
    """One ``(first file, reason)`` per series (and reason) not used, in path order."""
    by: dict[tuple[str, str], list[_Cine]] = defaultdict(list)
    for c in cines:
        if c.why:
            by[(c.first.series_uid or c.first.path, c.why)].append(c)
    out = []
    for (_, why), cs in by.items():
        f = cs[0].first
        files = sorted(i.path for c in cs for i in c.imgs)
        desc = f' {f.description!r}' if f.description else ''
        planes = f', {len(cs)} planes' if len(cs) > 1 else ''
        out.append(
            (
                files[0],
                f'series {f.series_uid or "(no SeriesInstanceUID)"}{desc} (SeriesNumber '
                f'{f.series_number}, {len(files)} image(s){planes}) not used: {why}',
            )
        )
    return sorted(out)


def read_dicom_dir(
    path, max_pixels: int = DEFAULT_MAX_PIXELS, study: str | None = None
) -> DicomReadResult:
    """
    Load the tagged cine study under a directory.

    Parameters
    ----------
    path : str or Path
        Directory, searched recursively (directory symlinks followed, each folder once); file
        names do not matter, hidden (``.*``) and system files (``Thumbs.db``, ``__MACOSX``, ...)
        are skipped.
    max_pixels : int
        Largest image accepted (Rows × Columns); a file declaring more is reported and skipped
        before its pixel data is read.
    study : str, optional
        StudyInstanceUID of the study to load; default (None or "") the study with the most
        tagged cines.

    Returns
    -------
    DicomReadResult
        ``frames`` (images in a :data:`WORKING_DTYPES` type: uint8/uint16 for unsigned 8/16-bit
        pixels without a rescale, float32 for every other stored type or with a rescale),
        ``problems`` (``(path, reason)``: skipped files, DICOMDIRs, links not followed, and once
        per series not used), ``warnings``, ``series``, ``long_axis``, the chosen ``study_uid``,
        ``studies``, ``choice``, ``complete`` and ``left_out``. Unpacks as ``frames, problems``.

    Raises
    ------
    FileNotFoundError
        ``path`` is not a directory.
    ValueError
        ``max_pixels`` is not a positive integer.
    DicomReadError
        The directory holds no files, no file yields a usable image, or ``study`` is not there
        (``.problems`` says why).

    Notes
    -----
    Files are read in sorted path order. Of two files holding the same instance (same
    SOPInstanceUID, or same series, plane, TriggerTime and InstanceNumber) the first keeps its
    place and the other is reported as a duplicate.

    Study selection: the images of each series and plane form a cine; cines are grouped by
    StudyInstanceUID and FrameOfReferenceUID, and an MR cine (≥ 2 images in time) is tagged when
    the spectrum of its ED image shows a tag grid (two peaks of one period, see
    :func:`_tag_grid`; a cine of the chosen study also when it shows one at the study's tag
    period). A group of ≥ 3 MR cines none of which passes votes on a grid or on tag lines they
    share in windows (tags on the heart alone, :data:`_TAG_STUDY`: noise-relative, ED and the
    next image). The group with the most clearly tagged cines is taken (whatever the file order),
    else one whose grid vote passes, else the one with the largest vote (ties go to more MR
    cines, more images, then the smaller UID), or the one ``study`` names. A taken study whose
    cines share one family of tag lines and no grid (:data:`_SINGLE_LINE_RATIO`) is a
    single-line study: its frames say so (``Frame.tag_lines``), and two single-line series of
    one slice whose lines cross are paired into one slice (:func:`_pair_line_series`: the
    second series' image of each phase is the frame's ``line_image``). A vote below the
    threshold takes all the group's MR cines, as does a group of the most MR cines when nothing
    votes; without any MR cine, every image as it is (Siemens MOSAIC images never). The tag test
    chooses, it does not thin the study: a cine of the taken group that fails it is not used at
    the place of a tagged cine (that one is), nor when
    its image is constant or it was acquired unlike every tagged cine (matrix, pixel spacing
    within 2 %); otherwise it is used, with a warning. Of the cines used, a slice acquired again
    in another series keeps the later acquisition (acquisition/series time, else SeriesNumber;
    where neither tells, the one with the most images, then the first by SeriesInstanceUID),
    with a warning. The study's phase count is the most common one: a cine with more phases
    gives the images nearest the study's trigger times, one with fewer gives each image the
    study phase nearest its trigger time (within a quarter phase interval, else it is left out,
    :data:`_FEWER_PHASES_TOL`). Every
    series not used is listed once in ``problems`` (and ``not_used``) with its reason.

    """
    if (
        isinstance(max_pixels, bool)
        or not isinstance(max_pixels, (int, np.integer))
        or max_pixels < 1
    ):
        raise ValueError(f'max_pixels must be a positive integer, got {max_pixels!r}')
    root = Path(path)
    if not root.is_dir():
        raise FileNotFoundError(f'DICOM directory not found: {root}')
    files, problems = _list_files(root)
    if not files:
        raise DicomReadError(f'no files under {root}: nothing to read', problems)
    images, unread = _read_images(files, int(max_pixels), problems)
    cines = _build_cines(images, problems)
    if not cines:
        raise DicomReadError(
            f'no usable DICOM image under {root} ({len(problems)} file(s) rejected; first: '
            f'{problems[0][0]}: {problems[0][1]})',
            problems,
        )
    sel = _select_study(cines, study, root, problems)
    problems += sel.problems
    if not sel.cines:
        raise DicomReadError(
            f'no usable cine under {root}: every series is left out ({len(sel.problems)} '
            'series; first: '
            f'{sel.problems[0][0]}: {sel.problems[0][1]})'
            if sel.problems
            else f'no usable cine under {root}: {sel.choice}',
            problems,
        )
    planes = sel.cines
    if sel.study_uid:  # MR images of the chosen study that could not be read are left out of it
        sel.left_out += [
            (f, f'an image of the study not read: {why}')
            for f, why in unread
            if _unread_image_of(f, sel.study_uid)
        ]
    sa_planes, la_planes, axis = _order_planes(planes)
    frames, series = _frames_and_series(sa_planes, la_planes, sel.tag_lines)
    studies = Counter(i.study_uid for p in planes for i in p.use if i.study_uid)
    return DicomReadResult(
        frames=frames,
        problems=problems,
        series=series,
        long_axis=axis,
        warnings=sel.warnings,
        study_uids=dict(studies.most_common()),
        study_uid=sel.study_uid,
        studies=sel.studies,
        choice=sel.choice,
        complete=not sel.left_out,
        left_out=sel.left_out,
        not_used=list(sel.problems),
    )


def _read_images(
    files: list[str], max_pixels: int, problems: list
) -> tuple[list[_Image], list[tuple[str, str]]]:
    """
    Read every file once, so that a copy of an instance (same SOPInstanceUID) is not read twice.

    Parameters
    ----------
    files : list of str
        Paths in the order they are read (sorted); of two copies the first is kept.
    max_pixels : int
        Largest image accepted (Rows × Columns).
    problems : list
        ``(path, reason)`` appended for each file skipped or duplicated.

    Returns
    -------
    images : list of _Image
        One per frame read.
    unread : list of (str, str)
        The files skipped and why.

    """
    images: list[_Image] = []
    unread: list[tuple[str, str]] = []
    first_with_uid: dict[tuple[str, int], str] = {}
    for f in files:
        imgs, why = _read_one(f, max_pixels)
        if imgs is None:
            problems.append((f, why))
            unread.append((f, why))
            continue
        for img in imgs:
            key = (img.sop_uid, img.frame)
            if img.sop_uid and key in first_with_uid:
                problems.append(
                    (f, f'duplicate instance: same SOPInstanceUID as {first_with_uid[key]}')
                )
                break
            if img.sop_uid:
                first_with_uid[key] = f
            images.append(img)
    return images, unread


def _build_cines(images: list[_Image], problems: list) -> list[_Cine]:
    """
    Group the images into cines (one per series and plane), in time order.

    An image of another size than most of its cine, or repeating one's TriggerTime and
    InstanceNumber, is reported in ``problems`` (``(path, reason)``) and left out.
    """
    groups: dict[tuple, list[_Image]] = defaultdict(list)
    for img in images:
        groups[_plane_key(img)].append(img)
    cines: list[_Cine] = []
    for imgs in groups.values():
        sizes = Counter(i.pixels.shape for i in imgs)
        ((shape, _),) = sizes.most_common(1)
        keep: list[_Image] = []
        seen: dict[tuple, str] = {}
        for i in imgs:
            phase_key = (round(i.trigger_ms, 3), i.instance)
            if i.pixels.shape != shape:
                problems.append(
                    (
                        i.path,
                        f'image size {i.pixels.shape[0]}x{i.pixels.shape[1]} differs '
                        f'from the rest of its series ({shape[0]}x{shape[1]})',
                    )
                )
            elif np.isfinite(i.trigger_ms) and i.instance is not None and phase_key in seen:
                problems.append(
                    (
                        i.path,
                        f'duplicate phase: same series, plane, TriggerTime and '
                        f'InstanceNumber as {seen[phase_key]}',
                    )
                )
            else:
                seen.setdefault(phase_key, i.path)
                keep.append(i)
        keep.sort(key=lambda i: (np.nan_to_num(i.trigger_ms, nan=np.inf), i.instance or 0, i.path))
        cines.append(_Cine(keep))
    return cines


def _order_planes(
    planes: list[_Cine],
) -> tuple[list[_Cine], list[_Cine], LongAxisEstimate | None]:
    """
    Split the cines into the short-axis stack and the long-axis views, each in its order.

    The short-axis stack is the largest cluster of parallel planes at ≥ 2 distinct positions,
    ordered base to apex along the long axis; long-axis views are ordered by SeriesNumber, then
    their angle about the axis (degrees, mod 180), then path.

    Parameters
    ----------
    planes : list of _Cine
        The cines used.

    Returns
    -------
    sa_planes, la_planes : list of _Cine
        Short-axis cines, base first, and long-axis cines.
    axis : LongAxisEstimate or None
        The estimated long axis (:func:`estimate_long_axis`).

    """
    normals = [p.first.geometry.normal for p in planes]
    clusters: list[list[int]] = []
    for i, n in enumerate(normals):
        for c in clusters:
            if abs(n @ normals[c[0]]) > _PARALLEL_COS:
                c.append(i)
                break
        else:
            clusters.append([i])

    def spread(c):
        pos = [planes[i].first.geometry.image_position @ normals[c[0]] for i in c]
        return len(set(np.round(pos, 1)))

    stacks = [c for c in clusters if spread(c) >= 2]
    sa_idx = set(max(stacks, key=len)) if stacks else set()
    sa_planes = [planes[i] for i in range(len(planes)) if i in sa_idx]
    la_planes = [planes[i] for i in range(len(planes)) if i not in sa_idx]
    axis = estimate_long_axis(
        [p.first.geometry for p in sa_planes],
        [p.first.geometry for p in la_planes],
        np.array([_fov_centre(p.first) for p in sa_planes]).reshape(-1, 3),
    )

    if axis is not None:
        sa_planes.sort(key=lambda p: -float(p.first.geometry.image_position @ axis.direction))
    ref = None
    if axis is not None:
        ref = np.cross(axis.direction, [1.0, 0.0, 0.0])
        if np.linalg.norm(ref) < 1e-3:
            ref = np.cross(axis.direction, [0.0, 1.0, 0.0])
        ref = _unit(ref)

    def la_key(p):
        ang = 0.0
        if ref is not None:
            n = p.first.geometry.normal
            n = n - (n @ axis.direction) * axis.direction
            ang = float(np.degrees(np.arctan2(np.cross(ref, n) @ axis.direction, ref @ n)) % 180.0)
        return (p.first.series_number, ang, p.first.path)

    la_planes.sort(key=la_key)
    return sa_planes, la_planes, axis


def _frames_and_series(
    sa_planes: list[_Cine], la_planes: list[_Cine], tag_lines: int = TAGS_GRID
) -> tuple[list[Frame], list[SeriesInfo]]:
    """
    Turn the ordered cines into frames (one per image) and a SeriesInfo per cine.

    A single-line study's frames say so (``tag_lines``); a cine paired with a second single-line
    series (``partner``) carries that series' image of the same phase as ``line_image``
    (``TAGS_LINE_PAIR``; a phase the partner lacks stays ``TAGS_LINES``).
    """
    frames: list[Frame] = []
    series: list[SeriesInfo] = []
    for view, group in ((VIEW_SA, sa_planes), (VIEW_LA, la_planes)):
        for idx, cine in enumerate(group):
            imgs, first = cine.use, cine.first
            trig, nominal = _timing(imgs, cine.phases, cine.num_phases)
            other = {}
            if cine.partner is not None:
                other = dict(zip(cine.partner.phases, cine.partner.use))
            for img, ph, t in zip(imgs, cine.phases, trig):
                line = other.get(ph)
                a, b = img.pixels, None if line is None else line.pixels
                if b is not None and b.dtype != a.dtype:
                    a, b = a.astype(np.float32), b.astype(np.float32)
                frames.append(
                    Frame(
                        image=a,
                        geometry=img.geometry,
                        view=view,
                        slice_index=idx,
                        phase_index=ph,
                        num_phases=cine.num_phases,
                        trigger_time=float(t),
                        cycle_duration=nominal,
                        series_uid=first.series_uid,
                        tag_lines=tag_lines if b is None else TAGS_LINE_PAIR,
                        line_image=b,
                    )
                )
            files = [i.path for i in imgs]
            if cine.partner is not None:
                files += [i.path for i in cine.partner.use]
            series.append(
                SeriesInfo(
                    series_uid=first.series_uid,
                    view=view,
                    slice_index=idx,
                    description=first.description,
                    series_number=first.series_number,
                    geometry=first.geometry,
                    files=files,
                    line_series_uid=(
                        '' if cine.partner is None else cine.partner.first.series_uid
                    ),
                )
            )
    return frames, series


def _phase_indices(imgs: list[_Image]) -> tuple[list[int], int, str | None]:
    """
    Phase index of each image of one cine (sorted by time), its phase count, and a warning.

    A cine with fewer images than its CardiacNumberOfImages has lost phases: where the
    InstanceNumbers place every image in one block of that many instances (1..N per series, or
    consecutive blocks per slice as some vendors number them), those give the phase indices, so
    later phases keep theirs; otherwise phases are numbered in time order and the gap is unplaced.
    """
    n = len(imgs)
    declared = Counter(i.cardiac_images for i in imgs if i.cardiac_images and i.cardiac_images > 0)
    total = declared.most_common(1)[0][0] if declared else 0
    if total <= n:
        return list(range(n)), n, None
    inst = [i.instance for i in imgs]
    if all(k is not None for k in inst):
        base = ((min(inst) - 1) // total) * total + 1
        idx = [k - base for k in inst]
        if all(0 <= k < total for k in idx) and all(a < b for a, b in zip(idx, idx[1:])):
            missing = sorted(set(range(total)) - set(idx))
            return (
                idx,
                total,
                (
                    f'phase(s) {", ".join(str(k + 1) for k in missing)} of {total} missing '
                    f'(CardiacNumberOfImages {total}, {n} image(s) found)'
                ),
            )
    return (
        list(range(n)),
        n,
        (
            f'{n} image(s) but CardiacNumberOfImages {total}: phase(s) missing, and the '
            f'InstanceNumbers do not say which; phases numbered in TriggerTime order'
        ),
    )


def _timing(imgs: list[_Image], phases: list[int], num_phases: int) -> tuple[np.ndarray, float]:
    """Trigger times (s) of one cine's images and its cycle duration (s, 0 = unknown)."""
    trig = np.array([i.trigger_ms for i in imgs]) / 1000.0
    nominal = imgs[0].nominal_ms / 1000.0 if imgs[0].nominal_ms > 0 else 0.0
    known = bool(np.all(np.isfinite(trig)))
    if nominal <= 0 and len(imgs) >= 2 and known:
        # Time per phase from neighbouring images (phase gaps count), extended to the last phase.
        per_phase = float(np.median(np.diff(trig) / np.diff(phases)))
        nominal = float(trig[-1] + per_phase * (num_phases - phases[-1]))
    if not known:
        trig = np.asarray(phases, dtype=np.float64) * (
            nominal / num_phases if nominal > 0 else 0.0
        )
    return trig, nominal
