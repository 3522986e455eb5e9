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
Classic single-frame MR files made into Enhanced MR multi-frame files, at test time.

Neither pydicom nor anything in the pinned requirements converts to Enhanced MR, so the functional
groups are written here, as a scanner writes them: the study/series attributes at the top level,
pixel measures and the rescale in the shared functional groups, and per frame its plane position
and orientation, its frame content (StackID, InStackPositionNumber, TemporalPositionIndex) and its
cardiac synchronisation (NominalCardiacTriggerDelayTime, RRIntervalTimeNominal). ``legacy=True``
writes a Legacy Converted Enhanced MR instead, whose per-frame TriggerTime and NominalInterval sit
in UnassignedPerFrameConvertedAttributesSequence (as legacy converters leave attributes that have
no functional group of their own).
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np
import pydicom
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.sequence import Sequence
from pydicom.uid import ExplicitVRLittleEndian, generate_uid

ENHANCED_MR = '1.2.840.10008.5.1.4.1.1.4.1'
LEGACY_CONVERTED_ENHANCED_MR = '1.2.840.10008.5.1.4.1.1.4.4'
#: Top-level attributes copied from the first classic file of a group.
_TOP = (
    'PatientName',
    'PatientID',
    'PatientBirthDate',
    'PatientSex',
    'StudyInstanceUID',
    'StudyDate',
    'StudyTime',
    'StudyID',
    'AccessionNumber',
    'ReferringPhysicianName',
    'Modality',
    'SeriesInstanceUID',
    'SeriesNumber',
    'SeriesDescription',
    'SeriesDate',
    'SeriesTime',
    'FrameOfReferenceUID',
    'PositionReferenceIndicator',
    'Manufacturer',
    'BodyPartExamined',
    'SamplesPerPixel',
    'PhotometricInterpretation',
    'Rows',
    'Columns',
    'BitsAllocated',
    'BitsStored',
    'HighBit',
    'PixelRepresentation',
)


def _item(**values) -> Dataset:
    ds = Dataset()
    for k, v in values.items():
        setattr(ds, k, v)
    return ds


def _seq(**values) -> Sequence:
    return Sequence([_item(**values)])


def write_enhanced(
    datasets: list[Dataset], path: Path, series_uid: str | None = None, legacy: bool = False
) -> Path:
    """
    Build one Enhanced MR file holding ``datasets`` as its frames.

    One Enhanced MR file holding ``datasets`` (classic single-frame MR images of one study)
    as its frames, in the given order; ``series_uid`` replaces theirs (default: the first's).

    Frames are grouped into stacks by orientation (StackID 1, 2, …) and numbered within their
    stack by position (InStackPositionNumber, 1-based) and time (TemporalPositionIndex: the
    rank of the TriggerTime within the plane, 1-based).
    """
    first = datasets[0]
    ds = Dataset()
    for k in _TOP:
        if k in first:
            setattr(ds, k, first.data_element(k).value)
    sop_class = LEGACY_CONVERTED_ENHANCED_MR if legacy else ENHANCED_MR
    ds.SOPClassUID, ds.SOPInstanceUID = sop_class, generate_uid(entropy_srcs=[str(path)])
    if series_uid:
        ds.SeriesInstanceUID = series_uid
    ds.InstanceNumber = 1
    ds.ImageType = ['ORIGINAL', 'PRIMARY', 'M', 'NONE']
    ds.ContentDate, ds.ContentTime = first.get('StudyDate', '20240101'), '120000'
    ds.AcquisitionDateTime = f'{ds.ContentDate}120000'
    ds.NumberOfFrames = len(datasets)
    shared = _item(
        PixelMeasuresSequence=_seq(
            PixelSpacing=list(first.PixelSpacing), SliceThickness=first.SliceThickness
        )
    )
    if 'RescaleSlope' in first:
        shared.PixelValueTransformationSequence = _seq(
            RescaleSlope=first.RescaleSlope,
            RescaleIntercept=first.RescaleIntercept,
            RescaleType='US',
        )
    ds.SharedFunctionalGroupsSequence = Sequence([shared])
    # Stacks by orientation, positions and times ranked within each.
    orient = [tuple(np.round(np.asarray(d.ImageOrientationPatient, float), 4)) for d in datasets]
    stack_of = {o: k + 1 for k, o in enumerate(dict.fromkeys(orient))}
    normal = {o: np.cross(o[:3], o[3:]) for o in stack_of}
    pos = [
        round(float(np.asarray(d.ImagePositionPatient, float) @ normal[o]), 2)
        for d, o in zip(datasets, orient)
    ]
    in_stack = {o: sorted({p for p, q in zip(pos, orient) if q == o}) for o in stack_of}
    times = defaultdict(list)
    for d, o, p in zip(datasets, orient, pos):
        times[(o, p)].append(float(d.TriggerTime))
    frames = []
    for d, o, p in zip(datasets, orient, pos):
        fg = _item(
            FrameContentSequence=_seq(
                StackID=str(stack_of[o]),
                InStackPositionNumber=in_stack[o].index(p) + 1,
                TemporalPositionIndex=sorted(times[(o, p)]).index(float(d.TriggerTime)) + 1,
            ),
            PlanePositionSequence=_seq(ImagePositionPatient=list(d.ImagePositionPatient)),
            PlaneOrientationSequence=_seq(ImageOrientationPatient=list(d.ImageOrientationPatient)),
        )
        if legacy:
            fg.UnassignedPerFrameConvertedAttributesSequence = _seq(
                TriggerTime=d.TriggerTime, NominalInterval=d.NominalInterval
            )
        else:
            fg.CardiacSynchronizationSequence = _seq(
                NominalCardiacTriggerDelayTime=d.TriggerTime,
                RRIntervalTimeNominal=d.NominalInterval,
            )
        frames.append(fg)
    ds.PerFrameFunctionalGroupsSequence = Sequence(frames)
    ds.PixelData = b''.join(
        np.asarray(d.pixel_array).astype(d.pixel_array.dtype.newbyteorder('<')).tobytes()
        for d in datasets
    )
    ds.file_meta = FileMetaDataset()
    ds.file_meta.MediaStorageSOPClassUID, ds.file_meta.MediaStorageSOPInstanceUID = (
        sop_class,
        ds.SOPInstanceUID,
    )
    ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
    path.parent.mkdir(parents=True, exist_ok=True)
    ds.save_as(path, enforce_file_format=True)
    return path


def convert_study(
    paths: list[Path], out: Path, per: str = 'cine', legacy: bool = False
) -> list[Path]:
    """
    Rewrite the classic files of a simulated study as Enhanced MR under ``out``.

    Classic files of a simulated study (``write_study_dicom``) as Enhanced MR under ``out``:
    ``per="cine"`` one file per series (its series UID kept), ``"stack"`` one file for every
    short-axis series and one for every long-axis one (new series UIDs), ``"frame"`` one
    single-frame Enhanced file per image (series UIDs kept).
    """
    groups: dict[str, list[Dataset]] = defaultdict(list)
    for p in sorted(paths):
        ds = pydicom.dcmread(p)
        key = {'cine': ds.SeriesInstanceUID, 'stack': p.parent.name[:2], 'frame': str(p)}[per]
        groups[key].append(ds)
    written = []
    for k, (key, datasets) in enumerate(sorted(groups.items())):
        datasets.sort(
            key=lambda d: (
                float(d.ImagePositionPatient[0]),
                float(d.ImagePositionPatient[1]),
                float(d.ImagePositionPatient[2]),
                float(d.TriggerTime),
            )
        )
        uid = generate_uid(entropy_srcs=['stack', key, str(out)]) if per == 'stack' else None
        written.append(
            write_enhanced(datasets, out / f'EMR_{k:03d}.dcm', series_uid=uid, legacy=legacy)
        )
    return written
