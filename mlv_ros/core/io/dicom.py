"""DICOM in and out for tagged cine MR: one file per image, one series per slice location.

Writing (:func:`write_study_dicom`): MR Image Storage, Explicit VR Little Endian, uint16 pixels
with ``RescaleSlope`` mapping back to the simulator's float intensities, and the geometry,
timing and identification attributes listed in the issue (IPP/IOP/PixelSpacing/SliceThickness,
TriggerTime in ms, CardiacNumberOfImages, NominalInterval, InstanceNumber = phase + 1,
SeriesDescription naming SA/LA).

Reading (:func:`read_dicom_dir`): every file under a directory (recursive, any name) is tried;
per-file problems (not DICOM, truncated, no pixels, missing geometry, size differing from the
rest of its series, …) are collected as ``(path, reason)`` while everything valid loads. Images
are grouped by series and plane, phases ordered by TriggerTime then InstanceNumber, and each
plane is classified from geometry alone: the largest group of parallel planes at distinct
positions is the short-axis stack, every other plane is long-axis. The long axis is estimated
from the LA planes' common line (or the SA normal), oriented apex → base with the anatomical
prior that the base lies right-posterior-superior of the apex (LPS ``(−1, 1, 1)`` side).
"""

from __future__ import annotations

import os
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pydicom
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.errors import InvalidDicomError
from pydicom.uid import ExplicitVRLittleEndian, MRImageStorage
from pydicom.valuerep import DSfloat

from mlv_ros.core.geometry import SliceGeometry
from mlv_ros.core.types import VIEW_LA, VIEW_NAMES, VIEW_SA, Frame

#: Stored value = round(intensity · PIXEL_SCALE); RescaleSlope = 1 / PIXEL_SCALE.
PIXEL_SCALE = 1000.0
_GEOMETRY_TAGS = ("ImagePositionPatient", "ImageOrientationPatient", "PixelSpacing")
_PARALLEL_COS = np.cos(np.radians(5.0))
_BASE_SIDE = np.array([-1.0, 1.0, 1.0]) / np.sqrt(3.0)


class DicomReadError(ValueError):
    """Nothing usable under the directory; ``problems`` lists ``(path, reason)`` per file."""

    def __init__(self, message: str, problems: list[tuple[str, str]] | None = None):
        super().__init__(message)
        self.problems = list(problems or [])


# ---------------------------------------------------------------------------------- writing
def _ds(v: float) -> DSfloat:
    return DSfloat(float(v), auto_format=True)


def write_study_dicom(study, out_dir, pixel_scale: float = PIXEL_SCALE, progress=None) -> list[Path]:
    """Write every frame of a simulated study as one DICOM file.

    Layout: ``out_dir/<SA|LA>_<index>/IM_<phase+1>.dcm``; any layout reads back the same way.

    Parameters
    ----------
    study : mlv_ros.core.sim.Study
        Simulated study (float images; myocardium M0 = 1).
    out_dir : str or Path
        Created if needed.
    pixel_scale : float
        Stored uint16 = round(intensity · pixel_scale), clipped to 0..65535.
    progress : callable, optional
        ``progress(done, total)`` after each file.

    Returns
    -------
    list of Path
        The written files, in frame order.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    series_number = {key: i + 1 for i, key in enumerate(study.keys)}
    paths = []
    total = len(study.frames)
    for n, fr in enumerate(study.frames):
        key = (fr.view, fr.slice_index)
        ds = frame_to_dataset(
            fr, pixel_scale=pixel_scale, study_uid=study.study_uid,
            frame_of_reference_uid=study.frame_of_reference_uid,
            series_number=series_number[key],
            description=study.descriptions.get(key, f"tagged {VIEW_NAMES[fr.view]} {fr.slice_index}"),
            patient_name=f"MLV^{study.preset['name']}")
        d = out / f"{VIEW_NAMES[fr.view]}_{fr.slice_index:02d}"
        d.mkdir(exist_ok=True)
        path = d / f"IM_{fr.phase_index + 1:04d}.dcm"
        ds.save_as(path, enforce_file_format=True)
        paths.append(path)
        if progress is not None:
            progress(n + 1, total)
    return paths


def frame_to_dataset(frame: Frame, pixel_scale: float = PIXEL_SCALE, study_uid: str = "",
                     frame_of_reference_uid: str = "", series_number: int = 1,
                     description: str = "", patient_name: str = "MLV^Phantom") -> Dataset:
    """DICOM dataset (MR Image Storage) of one frame; see the module docstring for the tags.

    Float images are stored as ``round(image · pixel_scale)`` with ``RescaleSlope =
    1/pixel_scale``; uint16 images are stored as they are (slope 1).
    """
    img = np.asarray(frame.image)
    if img.ndim != 2:
        raise ValueError(f"frame image must be 2-D, got shape {img.shape}")
    if img.dtype == np.uint16:
        stored, slope = img, 1.0
    else:
        stored = np.clip(np.rint(img.astype(np.float64) * pixel_scale), 0, 65535).astype(np.uint16)
        slope = 1.0 / pixel_scale
    g = frame.geometry
    sop_uid = pydicom.uid.generate_uid(
        entropy_srcs=[frame.series_uid, str(frame.phase_index), str(frame.slice_index)])
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = MRImageStorage
    meta.MediaStorageSOPInstanceUID = sop_uid
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = Dataset()
    ds.file_meta = meta
    ds.SOPClassUID = MRImageStorage
    ds.SOPInstanceUID = sop_uid
    ds.StudyInstanceUID = study_uid or pydicom.uid.generate_uid()
    ds.SeriesInstanceUID = frame.series_uid or pydicom.uid.generate_uid()
    ds.FrameOfReferenceUID = frame_of_reference_uid or pydicom.uid.generate_uid()
    ds.Modality = "MR"
    ds.Manufacturer = "mlv_ros simulator"
    ds.PatientName = patient_name
    ds.PatientID = "MLV-PHANTOM"
    ds.StudyDescription = "Simulated tagged cine MR (SPAMM)"
    ds.SeriesDescription = description
    ds.SeriesNumber = int(series_number)
    ds.InstanceNumber = int(frame.phase_index) + 1
    ds.ImageType = ["DERIVED", "PRIMARY", "TAGGING"]
    ds.ScanningSequence = "GR"
    ds.SequenceVariant = "SP"
    ds.MRAcquisitionType = "2D"
    ds.TriggerTime = _ds(frame.trigger_time * 1000.0)
    ds.NominalInterval = _ds(frame.cycle_duration * 1000.0)
    ds.CardiacNumberOfImages = int(frame.num_phases)
    ds.ImagePositionPatient = [_ds(v) for v in g.image_position]
    ds.ImageOrientationPatient = [_ds(v) for v in np.concatenate([g.row_direction, g.column_direction])]
    ds.PixelSpacing = [_ds(g.row_spacing), _ds(g.column_spacing)]
    ds.SliceThickness = _ds(g.slice_thickness)
    ds.SliceLocation = _ds(float(g.image_position @ g.normal))
    ds.Rows, ds.Columns = stored.shape
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.BitsAllocated = 16
    ds.BitsStored = 16
    ds.HighBit = 15
    ds.PixelRepresentation = 0
    ds.RescaleIntercept = _ds(0.0)
    ds.RescaleSlope = _ds(slope)
    ds.RescaleType = "US"
    ds.WindowCenter = _ds(0.6 * pixel_scale)
    ds.WindowWidth = _ds(1.2 * pixel_scale)
    ds.PixelData = np.ascontiguousarray(stored).tobytes()
    return ds


# ---------------------------------------------------------------------------------- reading
@dataclass
class LongAxisEstimate:
    """Long axis recovered from the image geometry.

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
    files: list[str]


@dataclass
class DicomReadResult:
    """Output of :func:`read_dicom_dir`; unpacks as ``frames, problems = result``.

    Attributes
    ----------
    frames : list of Frame
        Ordered by view (SA first), slice index, phase.
    problems : list of (str, str)
        ``(path, reason)`` for every file or series that was skipped.
    series : list of SeriesInfo
    long_axis : LongAxisEstimate or None
    """

    frames: list[Frame]
    problems: list[tuple[str, str]]
    series: list[SeriesInfo] = field(default_factory=list)
    long_axis: LongAxisEstimate | None = None

    def __iter__(self):
        yield self.frames
        yield self.problems


@dataclass
class _Image:
    path: str
    ds: Dataset
    pixels: np.ndarray
    geometry: SliceGeometry


def _float_list(ds, name, n):
    v = ds.get(name)
    if v is None:
        return None
    vals = [float(x) for x in (v if isinstance(v, (list, pydicom.multival.MultiValue)) else [v])]
    return vals if len(vals) == n else None


def _read_one(path: str) -> tuple[_Image | None, str | None]:
    """Load one file; returns (image, None) or (None, reason)."""
    try:
        ds = pydicom.dcmread(path)
    except InvalidDicomError as exc:
        return None, f"not a DICOM file ({exc})"
    except Exception as exc:  # pydicom raises many types on damaged files
        return None, f"unreadable DICOM ({type(exc).__name__}: {exc})"
    if "PixelData" not in ds:
        meta = getattr(ds, "file_meta", None)
        sop = ds.get("SOPClassUID") or (meta.get("MediaStorageSOPClassUID") if meta else None)
        name = getattr(sop, "name", str(sop)) if sop else ""
        if "Image" in name or "Rows" in ds:
            return None, f"no pixel data in an image object ({name or 'Rows present'}): truncated file?"
        if not sop:
            return None, "no pixel data and no SOP class (truncated or not an image)"
        return None, f"no pixel data (non-image DICOM: {name})"
    missing = [t for t in _GEOMETRY_TAGS if t not in ds]
    if missing:
        return None, f"missing geometry tag(s): {', '.join(missing)}"
    ipp = _float_list(ds, "ImagePositionPatient", 3)
    iop = _float_list(ds, "ImageOrientationPatient", 6)
    ps = _float_list(ds, "PixelSpacing", 2)
    if ipp is None or iop is None or ps is None:
        return None, "malformed geometry (ImagePositionPatient needs 3 values, " \
                     "ImageOrientationPatient 6, PixelSpacing 2)"
    try:
        pixels = ds.pixel_array
    except Exception as exc:
        return None, f"pixel data unreadable ({type(exc).__name__}: {exc})"
    if pixels.ndim != 2:
        return None, f"expected one 2-D greyscale frame, got pixel array of shape {pixels.shape}"
    slope = float(ds.get("RescaleSlope", 1.0) or 1.0)
    inter = float(ds.get("RescaleIntercept", 0.0) or 0.0)
    if slope != 1.0 or inter != 0.0:
        pixels = (pixels.astype(np.float64) * slope + inter).astype(np.float32)
    row = np.asarray(iop[:3])
    col = np.asarray(iop[3:])
    try:
        # Scanners write IOP to ~6 digits; re-orthonormalise before the strict SliceGeometry check.
        row = row / np.linalg.norm(row)
        col = col - (col @ row) * row
        col = col / np.linalg.norm(col)
        thick = float(ds.get("SliceThickness", 0) or 0) or min(ps)
        geom = SliceGeometry(np.asarray(ipp), row, col, ps[0], ps[1], thick)
    except (ValueError, FloatingPointError, ZeroDivisionError) as exc:
        return None, f"invalid geometry ({exc})"
    return _Image(path, ds, pixels, geom), None


def _plane_key(img: _Image) -> tuple:
    g = img.geometry
    n = g.normal
    return (str(img.ds.get("SeriesInstanceUID", "")),
            tuple(np.round(np.concatenate([g.row_direction, g.column_direction]), 3)),
            round(float(g.image_position @ n), 1))


def _trigger_ms(ds) -> float:
    v = ds.get("TriggerTime")
    try:
        return float(v) if v is not None and str(v) != "" else np.nan
    except (TypeError, ValueError):
        return np.nan


def _unit(v):
    return v / np.linalg.norm(v)


def estimate_long_axis(sa: list[SliceGeometry], la: list[SliceGeometry],
                       sa_centres: np.ndarray | None = None) -> LongAxisEstimate | None:
    """Long axis from SA and LA plane geometry (see module docstring).

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
            d, source = d_sa, "sa_normal"
        else:
            source = "la_planes"
        # Point on the LA planes' common line closest to the SA centre (weak pull along d).
        A = np.vstack([N, 1e-3 * np.eye(3)])
        b = np.concatenate([[n @ g.image_position for n, g in zip(N, la)], 1e-3 * centre])
        point = np.linalg.lstsq(A, b, rcond=None)[0]
        point = point + ((centre - point) @ d) * d
    elif d_sa is not None:
        d, source, point = d_sa, "sa_normal", centre
    else:
        return None
    if d @ _BASE_SIDE < 0:
        d = -d
    return LongAxisEstimate(point=point, direction=_unit(d), source=source)


def _fov_centre(img: _Image) -> np.ndarray:
    rows, cols = img.pixels.shape
    return img.geometry.pixel_to_patient(np.array([(rows - 1) / 2.0, (cols - 1) / 2.0]))


def read_dicom_dir(path) -> DicomReadResult:
    """Load every tagged cine image under a directory.

    Parameters
    ----------
    path : str or Path
        Directory, searched recursively; file names do not matter.

    Returns
    -------
    DicomReadResult
        ``frames`` (float32 if the files carry a rescale, else the stored dtype), ``problems``
        (``(path, reason)``), ``series`` and ``long_axis``. Unpacks as ``frames, problems``.

    Raises
    ------
    FileNotFoundError
        ``path`` is not a directory.
    DicomReadError
        The directory holds no files, or no file yields a usable image (``.problems`` says why).
    """
    root = Path(path)
    if not root.is_dir():
        raise FileNotFoundError(f"DICOM directory not found: {root}")
    files = sorted(str(Path(dp) / f) for dp, _, fs in os.walk(root) for f in fs)
    if not files:
        raise DicomReadError(f"no files under {root}: nothing to read")
    problems: list[tuple[str, str]] = []
    images: list[_Image] = []
    for f in files:
        img, why = _read_one(f)
        if img is None:
            problems.append((f, why))
        else:
            images.append(img)

    groups: dict[tuple, list[_Image]] = defaultdict(list)
    for img in images:
        groups[_plane_key(img)].append(img)
    planes = []
    for key, imgs in groups.items():
        sizes = Counter(i.pixels.shape for i in imgs)
        (shape, _), = sizes.most_common(1)
        keep = []
        for i in imgs:
            if i.pixels.shape != shape:
                problems.append((i.path, f"image size {i.pixels.shape[0]}x{i.pixels.shape[1]} differs "
                                         f"from the rest of its series ({shape[0]}x{shape[1]})"))
            else:
                keep.append(i)
        keep.sort(key=lambda i: (np.nan_to_num(_trigger_ms(i.ds), nan=np.inf),
                                 int(i.ds.get("InstanceNumber", 0) or 0), i.path))
        planes.append(keep)
    if not planes:
        raise DicomReadError(
            f"no usable DICOM image under {root} ({len(problems)} file(s) rejected; first: "
            f"{problems[0][0]}: {problems[0][1]})", problems)

    # Classify: largest cluster of parallel planes at >= 2 distinct positions = SA stack.
    normals = [p[0].geometry.normal for p in planes]
    clusters: list[list[int]] = []
    for i, n in enumerate(normals):
        for c in clusters:
            if abs(n @ normals[c[0]]) > _PARALLEL_COS:
                c.append(i)
                break
        else:
            clusters.append([i])

    def spread(c):
        pos = [planes[i][0].geometry.image_position @ normals[c[0]] for i in c]
        return len(set(np.round(pos, 1)))

    stacks = [c for c in clusters if spread(c) >= 2]
    sa_idx = set(max(stacks, key=len)) if stacks else set()
    sa_planes = [planes[i] for i in range(len(planes)) if i in sa_idx]
    la_planes = [planes[i] for i in range(len(planes)) if i not in sa_idx]
    axis = estimate_long_axis([p[0].geometry for p in sa_planes], [p[0].geometry for p in la_planes],
                              np.array([_fov_centre(p[0]) for p in sa_planes]).reshape(-1, 3))

    if axis is not None:
        sa_planes.sort(key=lambda p: -float(p[0].geometry.image_position @ axis.direction))
    ref = None
    if axis is not None:
        ref = np.cross(axis.direction, [1.0, 0.0, 0.0])
        if np.linalg.norm(ref) < 1e-3:
            ref = np.cross(axis.direction, [0.0, 1.0, 0.0])
        ref = _unit(ref)

    def la_key(p):
        ds = p[0].ds
        ang = 0.0
        if ref is not None:
            n = p[0].geometry.normal
            n = n - (n @ axis.direction) * axis.direction
            ang = float(np.degrees(np.arctan2(np.cross(ref, n) @ axis.direction, ref @ n)) % 180.0)
        return (int(ds.get("SeriesNumber", 0) or 0), ang, p[0].path)

    la_planes.sort(key=la_key)

    frames: list[Frame] = []
    series: list[SeriesInfo] = []
    for view, group in ((VIEW_SA, sa_planes), (VIEW_LA, la_planes)):
        for idx, imgs in enumerate(group):
            ds0 = imgs[0].ds
            trig = np.array([_trigger_ms(i.ds) for i in imgs]) / 1000.0
            nominal = float(ds0.get("NominalInterval", 0) or 0) / 1000.0
            if nominal <= 0 and len(imgs) >= 2 and np.all(np.isfinite(trig)):
                nominal = float(trig[-1] + np.median(np.diff(trig)))
            if not np.all(np.isfinite(trig)):
                trig = np.arange(len(imgs)) * (nominal / len(imgs) if nominal > 0 else 0.0)
            uid = str(ds0.get("SeriesInstanceUID", ""))
            for ph, (img, t) in enumerate(zip(imgs, trig)):
                frames.append(Frame(image=img.pixels, geometry=img.geometry, view=view,
                                    slice_index=idx, phase_index=ph, num_phases=len(imgs),
                                    trigger_time=float(t), cycle_duration=nominal, series_uid=uid))
            series.append(SeriesInfo(series_uid=uid, view=view, slice_index=idx,
                                     description=str(ds0.get("SeriesDescription", "")),
                                     series_number=int(ds0.get("SeriesNumber", 0) or 0),
                                     geometry=imgs[0].geometry, files=[i.path for i in imgs]))
    return DicomReadResult(frames=frames, problems=problems, series=series, long_axis=axis)
