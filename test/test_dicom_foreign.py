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
DICOM as other writers make it (pixels, transfer syntaxes, folders).

The corpus is built at test time: our simulated study re-encoded by pydicom (every stored pixel
type with a rescale, no rescale, MONOCHROME1, big endian, RLE / JPEG-LS / JPEG 2000 lossless,
deflate, JPEG baseline, colour, a syntax nothing decodes), laid out as exports are (directory
symlinks, link loops, hidden and system files, a DICOMDIR media layout), plus files pydicom ships
in its wheel (``get_testdata_file(..., download=False)``: never a download). Each case has its
outcome: the same frames (bit-identical where the encoding is lossless), or a reason.
"""

import io
import json
import os
from pathlib import Path
import shutil
import subprocess
import sys
from types import SimpleNamespace

from corpus.dicom_cases import frames_by_path, set_float_pixels
from mlv_ros import conversions
from mlv_ros.core.io import read_dicom_dir, WORKING_DTYPES, write_study_dicom
from mlv_ros.core.sim import simulate_study
import numpy as np
import pydicom
from pydicom.data import get_testdata_file
from pydicom.encaps import encapsulate
from pydicom.fileset import FileSet
from pydicom.uid import (
    DeflatedExplicitVRLittleEndian,
    ExplicitVRBigEndian,
    generate_uid,
    JPEG2000Lossless,
    JPEG2000MCLossless,
    JPEGBaseline8Bit,
    JPEGLSLossless,
    RLELossless,
)
from pydicom.valuerep import DSfloat
import pytest

pytestmark = pytest.mark.slow  # a graph run: scheduled first (conftest)

RESCALE_TAGS = ('RescaleSlope', 'RescaleIntercept', 'RescaleType')


@pytest.fixture(scope='module')
def study(tmp_path_factory):
    """Return a small study as our writer makes it (uint16, RescaleSlope 0.001) and its frames."""
    root = tmp_path_factory.mktemp('foreign')
    sim = simulate_study('normal', snr=20.0, size=48, num_phases=3, subplanes=1, seed=2)
    paths = write_study_dicom(sim, root / 'study')
    ref = read_dicom_dir(root / 'study')
    assert ref.problems == [] and len(ref.frames) == len(paths) == 33
    return SimpleNamespace(
        root=root, dir=root / 'study', paths=paths, ref=ref, by_path=frames_by_path(ref)
    )


def _key(fr):
    return fr.series_uid, fr.view, fr.slice_index, fr.phase_index


def _rewrite(study, out: Path, edit, only=None) -> list[Path]:
    """
    Re-encode every study file by ``edit(ds)`` to the same relative path under ``out``.

    Every study file (or those under ``only``, a folder name) re-encoded by ``edit(ds)`` to the
    same relative path under ``out``.
    """
    written = []
    for p in study.paths:
        rel = p.relative_to(study.dir)
        if only is not None and rel.parts[0] != only:
            continue
        ds = pydicom.dcmread(p)
        edit(ds)
        q = out / rel
        q.parent.mkdir(parents=True, exist_ok=True)
        pydicom.dcmwrite(q, ds, enforce_file_format=True)  # encoded as its file meta says
        written.append(q)
    return written


def _sources(study, files: list[Path]) -> list[tuple[Path, Path]]:
    """``(copy, original)`` pairs: each rewritten file with the study file it came from."""
    return [
        (f, study.dir.joinpath(*f.relative_to(study.root).parts[1:])) for f in files
    ]  # root/<copy>/<rel>


def _stored(ds) -> np.ndarray:
    return ds.pixel_array.astype(np.int64)


def _set_stored(ds, values: np.ndarray, dtype, slope=None, intercept=None) -> None:
    """Store ``values`` as integer ``dtype`` pixels, with a rescale or (slope None) without one."""
    dt = np.dtype(dtype)
    ds.BitsAllocated = ds.BitsStored = 8 * dt.itemsize
    ds.HighBit = ds.BitsStored - 1
    ds.PixelRepresentation = int(dt.kind == 'i')
    ds.PixelData = np.ascontiguousarray(values, dt.newbyteorder('<')).tobytes()
    ds['PixelData'].VR = 'OB' if dt.itemsize == 1 else 'OW'
    for tag in RESCALE_TAGS:
        if tag in ds:
            delattr(ds, tag)
    if slope is not None:
        ds.RescaleSlope = DSfloat(slope, auto_format=True)
        ds.RescaleIntercept = DSfloat(intercept, auto_format=True)


def _expected(path: Path) -> np.ndarray:
    """Return what a file holds, rescaled in float64 and rounded once to float32."""
    ds = pydicom.dcmread(path)
    slope, inter = float(ds.get('RescaleSlope', 1.0)), float(ds.get('RescaleIntercept', 0.0))
    return (ds.pixel_array.astype(np.float64) * slope + inter).astype(np.float32)


def _assert_publishable(res) -> None:
    """Every frame has a working type that frame_source can publish (sensor_msgs/Image)."""
    for fr in res.frames:
        assert fr.image.dtype in WORKING_DTYPES and fr.image.dtype.isnative
        msg = conversions.image_to_msg(fr.image)
        assert np.array_equal(conversions.msg_to_image(msg), fr.image)


# (stored dtype, stored values from the study's uint16 s, slope, intercept): each maps back to
# 0.001 · s within its own quantisation (slope / 2).
TYPE_CASES = {
    'uint8': (np.uint8, lambda s: np.rint(s / 257.0), 0.257, 0.0),
    'int8': (np.int8, lambda s: np.rint(s / 257.0) - 128, 0.257, 128 * 0.257),
    'uint16': (np.uint16, lambda s: s, 0.001, 0.0),
    'int16': (np.int16, lambda s: s - 32768, 0.001, 32.768),
    'uint32': (np.uint32, lambda s: s * 65536, 0.001 / 65536, 0.0),
    'int32': (np.int32, lambda s: s * 65536 - 2**31, 0.001 / 65536, 32.768),
}


def test_every_stored_type_with_a_rescale_reads_as_the_same_frames(study):
    for name, (dtype, to_stored, slope, inter) in TYPE_CASES.items():
        out = study.root / f'type_{name}'
        files = _rewrite(
            study, out, lambda ds: _set_stored(ds, to_stored(_stored(ds)), dtype, slope, inter)
        )
        res = read_dicom_dir(out)
        assert res.problems == [] and len(res.frames) == 33, name
        got = frames_by_path(res)
        for f, p in _sources(study, files):
            img, ref = got[str(f)].image, study.by_path[str(p)].image
            assert img.dtype == np.float32, name
            assert np.array_equal(img, _expected(f)), name  # rescaled once, in float64
            np.testing.assert_allclose(img, ref, rtol=0, atol=slope / 2 + 1e-5, err_msg=name)
        if name == 'uint16':  # the writer's own encoding: bit-identical
            assert all(
                np.array_equal(got[str(f)].image, study.by_path[str(p)].image)
                for f, p in _sources(study, files)
            )
    for name, double in (('float32', False), ('float64', True)):
        out = study.root / f'type_{name}'
        files = _rewrite(study, out, lambda ds: set_float_pixels(ds, _stored(ds) * 0.001, double))
        res = read_dicom_dir(out)
        assert res.problems == [] and len(res.frames) == 33, name
        got = frames_by_path(res)
        for f, p in _sources(study, files):
            img = got[str(f)].image
            assert img.dtype == np.float32 and np.array_equal(img, study.by_path[str(p)].image), (
                name
            )


def test_pixels_without_a_rescale_load_in_a_publishable_type(study):
    """int16 without a rescale used to kill frame_source (no image encoding for dtype int16)."""
    cases = {
        'int16': (lambda s: s - 32768, np.int16, None, np.float32),
        'uint32': (lambda s: s * 65536, np.uint32, None, np.float32),
        'uint16_big_endian': (lambda s: s, np.uint16, ExplicitVRBigEndian, np.uint16),
    }
    for name, (to_stored, dtype, syntax, working) in cases.items():
        out = study.root / f'raw_{name}'

        def edit(ds):
            values = to_stored(_stored(ds))
            _set_stored(ds, values, dtype)
            if syntax is not None:
                ds.file_meta.TransferSyntaxUID = syntax
                ds.PixelData = np.asarray(values, np.dtype(dtype).newbyteorder('>')).tobytes()

        files = _rewrite(study, out, edit, only='SA_00')
        res = read_dicom_dir(out)
        assert res.problems == [] and len(res.frames) == 3, name
        got = frames_by_path(res)
        for f, p in _sources(study, files):
            want = to_stored(pydicom.dcmread(p).pixel_array.astype(np.int64))
            assert got[str(f)].image.dtype == working, name
            assert np.array_equal(got[str(f)].image, want.astype(working)), name
        _assert_publishable(res)


def test_monochrome1_is_inverted(study):
    # Stored inverted and labelled MONOCHROME1 (as a CR/DX-style writer would): the same frames.
    def relabel_inverted(ds):
        ds.PixelData = (65535 - ds.pixel_array).astype('<u2').tobytes()
        ds.PhotometricInterpretation = 'MONOCHROME1'

    files = _rewrite(study, study.root / 'mono1_inverted', relabel_inverted)
    got = frames_by_path(read_dicom_dir(study.root / 'mono1_inverted'))
    for f, p in _sources(study, files):
        assert np.array_equal(got[str(f)].image, study.by_path[str(p)].image)
    # The same stored values relabelled: read as their inverse within the stored 16 bits.
    files = _rewrite(
        study,
        study.root / 'mono1_relabelled',
        lambda ds: setattr(ds, 'PhotometricInterpretation', 'MONOCHROME1'),
        only='SA_00',
    )
    got = frames_by_path(read_dicom_dir(study.root / 'mono1_relabelled'))
    for f in files:
        s = pydicom.dcmread(f).pixel_array.astype(np.float64)
        assert np.array_equal(got[str(f)].image, ((65535 - s) * 0.001).astype(np.float32))

    # 12 bits stored, no rescale: inverted within 0..4095, and still uint16.
    def twelve_bits(ds):
        _set_stored(ds, _stored(ds) >> 4, np.uint16)
        ds.BitsStored, ds.HighBit = 12, 11
        ds.PhotometricInterpretation = 'MONOCHROME1'

    files = _rewrite(study, study.root / 'mono1_12bit', twelve_bits, only='SA_00')
    got = frames_by_path(read_dicom_dir(study.root / 'mono1_12bit'))
    for f, p in _sources(study, files):
        want = 4095 - (pydicom.dcmread(p).pixel_array >> 4)
        assert got[str(f)].image.dtype == np.uint16 and np.array_equal(got[str(f)].image, want)


def test_lossless_compressed_copies_are_bit_identical(study):
    for syntax in (RLELossless, JPEGLSLossless, JPEG2000Lossless, DeflatedExplicitVRLittleEndian):
        out = study.root / f'syntax_{syntax.keyword}'

        def edit(ds):
            if syntax.is_compressed:
                ds.compress(
                    syntax
                )  # RLE: pydicom; JPEG-LS: pyjpegls; JPEG 2000: pylibjpeg-openjpeg
            else:
                ds.file_meta.TransferSyntaxUID = syntax

        files = _rewrite(study, out, edit)
        assert (
            pydicom.dcmread(files[0], stop_before_pixels=True).file_meta.TransferSyntaxUID
            == syntax
        )
        res = read_dicom_dir(out)
        assert res.problems == [], syntax.name
        assert sorted(map(_key, res.frames)) == sorted(map(_key, study.ref.frames))
        got = frames_by_path(res)
        for f, p in _sources(study, files):
            a, b = got[str(f)].image, study.by_path[str(p)].image
            assert a.dtype == b.dtype and np.array_equal(a, b), (syntax.name, f)

    # Signed 16-bit pixels compressed losslessly: as their uncompressed copy.
    def signed(ds):
        _set_stored(ds, _stored(ds) - 32768, np.int16, 0.001, 32.768)

    plain = _rewrite(study, study.root / 'signed_plain', signed, only='SA_01')
    want = frames_by_path(read_dicom_dir(study.root / 'signed_plain'))
    for syntax in (JPEGLSLossless, JPEG2000Lossless):
        out = study.root / f'signed_{syntax.keyword}'
        files = _rewrite(study, out, lambda ds: (signed(ds), ds.compress(syntax)), only='SA_01')
        res = read_dicom_dir(out)
        assert res.problems == [], syntax.name
        got = frames_by_path(res)
        for f, q in zip(files, plain):
            ds = pydicom.dcmread(f, stop_before_pixels=True)
            assert ds.PixelRepresentation == 1 and ds.file_meta.TransferSyntaxUID == syntax
            assert np.array_equal(got[str(f)].image, want[str(q)].image), (syntax.name, f)
    # pydicom's own compressed copies of MR_small.dcm (int16, no rescale): the same frame.
    plain = study.root / 'mr_small_plain'
    plain.mkdir()
    shutil.copy(get_testdata_file('MR_small.dcm', download=False), plain)
    want = read_dicom_dir(plain).frames[0].image
    assert want.dtype == np.float32
    for name in (
        'MR_small_RLE.dcm',
        'MR_small_jpeg_ls_lossless.dcm',
        'MR_small_jp2klossless.dcm',
        'MR_small_bigendian.dcm',
    ):
        d = study.root / f'mr_small_{name}'
        d.mkdir()
        shutil.copy(get_testdata_file(name, download=False), d)
        res = read_dicom_dir(d)
        assert res.problems == [] and np.array_equal(res.frames[0].image, want), name


def _gdcm_copy(src: Path, dst: Path, syntax: str) -> None:
    """
    Transcode ``src`` by GDCM to the transfer syntax ``gdcm.TransferSyntax.<syntax>``.

    ``src`` transcoded by GDCM (python-gdcm: an encoder independent of pydicom and its plugins)
    to the transfer syntax ``gdcm.TransferSyntax.<syntax>``, written to ``dst``.
    """
    import gdcm

    reader = gdcm.ImageReader()
    reader.SetFileName(str(src))
    assert reader.Read(), src
    change = gdcm.ImageChangeTransferSyntax()
    change.SetTransferSyntax(gdcm.TransferSyntax(getattr(gdcm.TransferSyntax, syntax)))
    change.SetInput(reader.GetImage())
    assert change.Change(), (src, syntax)
    dst.parent.mkdir(parents=True, exist_ok=True)
    writer = gdcm.ImageWriter()
    writer.SetFileName(str(dst))
    writer.SetFile(reader.GetFile())
    writer.SetImage(change.GetOutput())
    assert writer.Write(), dst


#: GDCM's lossless JPEG encoders: JPEG Lossless SV1 (Process 14, first-order prediction; the
#: usual PACS export), Process 14 with any predictor, JPEG-LS lossless.
GDCM_LOSSLESS = {
    'JPEGLosslessProcess14_1': '1.2.840.10008.1.2.4.70',
    'JPEGLosslessProcess14': '1.2.840.10008.1.2.4.57',
    'JPEGLSLossless': '1.2.840.10008.1.2.4.80',
}


def test_copies_compressed_by_gdcm_are_bit_identical(study):
    """
    Check the study transcoded by GDCM to each lossless JPEG syntax: frames bit-identical.

    The study transcoded by GDCM to each lossless JPEG syntax, unsigned (uint16 with a rescale)
    and signed (int16): every frame bit-identical to the uncompressed file's.
    """

    def signed(ds):
        _set_stored(ds, _stored(ds) - 32768, np.int16, 0.001, 32.768)

    plain_signed = _rewrite(study, study.root / 'gdcm_signed_plain', signed, only='SA_03')
    want_signed = frames_by_path(read_dicom_dir(study.root / 'gdcm_signed_plain'))
    for name, uid in GDCM_LOSSLESS.items():
        out = study.root / f'gdcm_{name}'
        files = [out / p.relative_to(study.dir) for p in study.paths]
        for src, dst in zip(study.paths, files):
            _gdcm_copy(src, dst, name)
        ds = pydicom.dcmread(files[0], stop_before_pixels=True)
        assert ds.file_meta.TransferSyntaxUID == uid and 'GDCM' in str(
            ds.file_meta.ImplementationVersionName
        )
        res = read_dicom_dir(out)
        assert res.problems == [] and res.complete, name
        got = frames_by_path(res)
        for f, p in zip(files, study.paths):
            a, b = got[str(f)].image, study.by_path[str(p)].image
            assert a.dtype == b.dtype and np.array_equal(a, b), (name, f)
        signed_out = study.root / f'gdcm_signed_{name}'
        copies = [signed_out / p.name for p in plain_signed]
        for src, dst in zip(plain_signed, copies):
            _gdcm_copy(src, dst, name)
        got = frames_by_path(read_dicom_dir(signed_out))
        for f, q in zip(copies, plain_signed):
            assert pydicom.dcmread(f, stop_before_pixels=True).PixelRepresentation == 1
            assert np.array_equal(got[str(f)].image, want_signed[str(q)].image), (name, f)


def test_a_run_on_a_jpeg_lossless_study_gives_the_same_motion(tmp_path):
    """
    Check that a study and its GDCM JPEG Lossless SV1 copy give the same motion in a graph run.

    One short graph run (2 phases, 200 particles) on a study and on its GDCM JPEG Lossless SV1
    copy: the same motion in every phase (bit-identical frames, a deterministic solver).
    """
    from mlv_ros.recording import read_run
    from mlv_ros.runner import run_graph

    sim = simulate_study('normal', snr=20.0, size=80, num_phases=2, subplanes=1, seed=3)
    plain = write_study_dicom(sim, tmp_path / 'plain')
    for p in plain:
        _gdcm_copy(
            p, tmp_path / 'sv1' / p.relative_to(tmp_path / 'plain'), 'JPEGLosslessProcess14_1'
        )
    runs = {}
    for name in ('plain', 'sv1'):
        summary = run_graph(
            {'source': 'dicom', 'path': str(tmp_path / name)},
            tmp_path / f'run_{name}',
            overrides={'registration': {'num_particles': 200}},
            timeout=240,
            progress=lambda *_: None,
        )
        assert summary['complete'], (name, summary)
        runs[name] = read_run(tmp_path / f'run_{name}' / 'run.mcap')
    a, b = runs['plain'], runs['sv1']
    assert sorted(a['positions']) == sorted(b['positions']) == [0, 1]
    worst = {
        k: float(np.max(np.abs(a['positions'][k] - b['positions'][k]))) for k in a['positions']
    }
    assert all(d == 0.0 for d in worst.values()), (
        f'largest position difference per phase (mm): {worst}'
    )


def test_lossy_jpeg_decodes(study):
    """Lossy 8-bit JPEG (Pillow's encoder): decoded to within the codec's error; 12-bit JPEG."""
    from PIL import Image

    def jpeg(ds):
        s8 = (ds.pixel_array >> 8).astype(np.uint8)
        buf = io.BytesIO()
        Image.fromarray(s8).save(buf, format='JPEG', quality=95)
        _set_stored(ds, s8, np.uint8, 0.256, 0.0)
        ds.PixelData = encapsulate([buf.getvalue()])
        ds['PixelData'].VR = 'OB'
        ds.file_meta.TransferSyntaxUID = JPEGBaseline8Bit
        ds.LossyImageCompression = '01'

    files = _rewrite(study, study.root / 'jpeg_baseline', jpeg, only='SA_02')
    res = read_dicom_dir(study.root / 'jpeg_baseline')
    assert res.problems == [] and len(res.frames) == 3
    got = frames_by_path(res)
    for f, p in _sources(study, files):
        want = (pydicom.dcmread(p).pixel_array >> 8) * 0.256
        err = np.abs(got[str(f)].image - want)
        assert got[str(f)].image.dtype == np.float32 and float(np.mean(err)) < 2 * 0.256
    # JPEG extended, 12 bits (pydicom's JPGExtended.dcm, given the plane geometry it lacks).
    ds = pydicom.dcmread(get_testdata_file('JPGExtended.dcm', download=False))
    assert ds.file_meta.TransferSyntaxUID == pydicom.uid.JPEGExtended12Bit and ds.BitsStored == 12
    ds.ImagePositionPatient, ds.ImageOrientationPatient, ds.PixelSpacing = (
        [0, 0, 0],
        [1, 0, 0, 0, 1, 0],
        [1, 1],
    )
    (study.root / 'jpeg_extended').mkdir()
    ds.save_as(study.root / 'jpeg_extended' / 'x.dcm', enforce_file_format=True)
    res = read_dicom_dir(study.root / 'jpeg_extended')
    assert res.problems == [] and res.frames[0].image.dtype == np.uint16
    assert (
        np.array_equal(res.frames[0].image, ds.pixel_array)
        and int(res.frames[0].image.max()) < 4096
    )


def _one_frame_copy(study, name: str, edit) -> Path:
    """Save the study's first file, edited, in a series of its own as ``name`` under the study."""
    ds = pydicom.dcmread(study.paths[0])
    ds.SeriesInstanceUID = generate_uid(entropy_srcs=['foreign series', name])
    ds.SOPInstanceUID = ds.file_meta.MediaStorageSOPInstanceUID = generate_uid(
        entropy_srcs=['foreign', name]
    )
    edit(ds)
    path = study.root / 'mixed' / name
    path.parent.mkdir(parents=True, exist_ok=True)
    ds.save_as(path, enforce_file_format=True)
    return path


def test_colour_and_undecodable_files_are_reported_and_the_study_loads(study):
    mixed = study.root / 'mixed'
    shutil.copytree(study.dir, mixed / 'study')

    def rgb_by_plane(ds):
        g = (ds.pixel_array >> 8).astype(np.uint8)
        _set_stored(ds, np.stack([g, g, g]), np.uint8)  # RRR…GGG…BBB
        ds.SamplesPerPixel, ds.PhotometricInterpretation, ds.PlanarConfiguration = 3, 'RGB', 1

    def palette(ds):
        ds.PhotometricInterpretation = 'PALETTE COLOR'

    def jpeg2000_part2(ds):
        ds.compress(JPEG2000Lossless)
        ds.file_meta.TransferSyntaxUID = JPEG2000MCLossless  # a syntax no pydicom plugin decodes

    expect = {
        _one_frame_copy(study, 'rgb_planar.dcm', rgb_by_plane): [
            'colour image',
            'SamplesPerPixel 3',
            'PlanarConfiguration 1 = colour-by-plane',
        ],
        _one_frame_copy(study, 'palette.dcm', palette): ['colour image', 'PALETTE COLOR'],
        _one_frame_copy(study, 'j2k_part2.dcm', jpeg2000_part2): [
            'JPEG 2000 Part 2',
            'has no decoder',
            'convert',
        ],
    }
    for name, reason in (
        ('examples_rgb_color.dcm', ['colour image', 'PlanarConfiguration 0']),
        ('examples_palette.dcm', ['colour image', 'PALETTE COLOR']),
        ('liver_1frame.dcm', ['BitsAllocated 1']),
        ('JPEG-lossy.dcm', ['missing geometry']),
    ):
        shutil.copy(get_testdata_file(name, download=False), mixed)
        expect[mixed / name] = reason
    res = read_dicom_dir(mixed)
    why = dict(res.problems)
    assert sorted(why) == sorted(map(str, expect))
    for path, parts in expect.items():
        assert all(part in why[str(path)] for part in parts), (path, why[str(path)])
    assert sorted(map(_key, res.frames)) == sorted(map(_key, study.ref.frames))
    got = frames_by_path(res)
    for p in study.paths:
        assert np.array_equal(
            got[str(mixed / 'study' / p.relative_to(study.dir))].image, study.by_path[str(p)].image
        )


def test_a_missing_decoder_is_reported_with_the_package_that_decodes(study):
    """
    Check that compressed files are reported naming the package when the plugins are missing.

    In an interpreter where the plugins cannot be imported (as without requirements/base.txt's
    decoder pins, and without python-gdcm, which pydicom also decodes with), compressed files are
    reported naming the package; the rest loads.
    """
    out = study.root / 'no_plugins'
    jls = _rewrite(study, out, lambda ds: ds.compress(JPEGLSLossless), only='SA_00')
    j2k = _rewrite(study, out, lambda ds: ds.compress(JPEG2000Lossless), only='SA_01')
    rle = _rewrite(
        study, out, lambda ds: ds.compress(RLELossless), only='SA_02'
    )  # pydicom's own decoder
    plain = _rewrite(study, out, lambda ds: None, only='SA_03')
    code = (
        'import json, sys\n'
        "for name in ('pylibjpeg', 'libjpeg', 'openjpeg', 'rle', 'jpeg_ls', 'PIL', 'gdcm'):\n"
        '    sys.modules[name] = None  # importing it now raises ImportError, as if not '
        'installed\n'
        'from mlv_ros.core.io import read_dicom_dir\n'
        'res = read_dicom_dir(sys.argv[1])\n'
        "print(json.dumps({'problems': res.problems, 'files': [f for s in res.series for f in "
        's.files]}))\n'
    )
    run = subprocess.run(
        [sys.executable, '-c', code, str(out)],
        capture_output=True,
        text=True,
        timeout=120,
        env=dict(os.environ, PYTHONWARNINGS='ignore'),
    )
    assert run.returncode == 0, run.stderr
    got = json.loads(run.stdout)
    why = dict(got['problems'])
    assert sorted(why) == sorted(map(str, jls + j2k))
    for f in jls:
        assert 'JPEG-LS Lossless' in why[str(f)] and 'no decoder plugin installed' in why[str(f)]
        assert 'pyjpegls' in why[str(f)] and 'requirements/base.txt' in why[str(f)]
    for f in j2k:
        assert 'JPEG 2000' in why[str(f)] and 'pylibjpeg-openjpeg' in why[str(f)]
    assert sorted(got['files']) == sorted(map(str, rle + plain))


def test_directory_symlinks_loops_hidden_and_system_files(study):
    root = study.root / 'links'
    shutil.copytree(study.dir, root)
    # An SA slice kept elsewhere and linked in (read silently as 80 of 88 frames before).
    elsewhere = study.root / 'elsewhere'
    shutil.move(root / 'SA_03', elsewhere / 'SA_03')
    (root / 'SA_03').symlink_to(elsewhere / 'SA_03', target_is_directory=True)
    (root / 'SA_00' / 'loop').symlink_to(root, target_is_directory=True)  # back to an ancestor
    (root / 'again').symlink_to(root / 'LA_00', target_is_directory=True)  # a second way in
    (root / 'broken').symlink_to(study.root / 'nowhere')
    os.mkfifo(root / 'pipe')  # reading it would block for ever
    # Hidden and system entries, skipped without a word (a hidden copy would be a duplicate).
    (root / '.DS_Store').write_bytes(b'\0\0\0\1Bud1' + bytes(100))
    (root / 'SA_01' / '._IM_0001.dcm').write_bytes(b'\0\5\26\7' + bytes(60))
    (root / 'Thumbs.db').write_bytes(bytes(64))
    (root / 'desktop.ini').write_text('[.ShellClassInfo]\n')
    shutil.copytree(root / 'LA_01', root / '.snapshot')
    (root / '__MACOSX').mkdir()
    (root / '__MACOSX' / '._SA_00').write_bytes(bytes(32))

    res = read_dicom_dir(root)
    why = dict(res.problems)
    assert sorted(why) == sorted(str(root / n) for n in ('SA_00/loop', 'again', 'broken', 'pipe'))
    assert 'symlink loop' in why[str(root / 'SA_00' / 'loop')]
    assert 'already read as' in why[str(root / 'again')] and why[str(root / 'again')].endswith(
        'not read twice'
    )
    assert 'broken symbolic link' in why[str(root / 'broken')]
    assert 'not a regular file' in why[str(root / 'pipe')]
    assert sorted(map(_key, res.frames)) == sorted(map(_key, study.ref.frames))
    got = frames_by_path(res)
    for p in study.paths:
        assert np.array_equal(
            got[str(root / p.relative_to(study.dir))].image, study.by_path[str(p)].image
        )


def test_dicomdir_exports_load_and_the_index_is_reported(study):
    export = study.root / 'export'
    fs = FileSet()
    for p in study.paths:
        ds = pydicom.dcmread(p)
        ds.StudyDate, ds.StudyTime, ds.StudyID = (
            '20240101',
            '120000',
            '1',
        )  # a STUDY record needs them
        fs.add(ds)
    fs.write(export)  # DICOMDIR + PT000000/ST000000/SE00000n/IM00000m, as on a CD
    res = read_dicom_dir(export)
    assert [p for p, _ in res.problems] == [str(export / 'DICOMDIR')]
    assert 'DICOMDIR' in res.problems[0][1] and 'ignored' in res.problems[0][1]
    assert 'lists 33 image file(s)' in res.problems[0][1] and 'missing' not in res.problems[0][1]
    assert sorted(map(_key, res.frames)) == sorted(map(_key, study.ref.frames))
    for fr in res.frames:
        ref = {_key(f): f for f in study.ref.frames}[_key(fr)]
        assert np.array_equal(fr.image, ref.image)
    # pydicom's own DICOMDIR alone beside the study: what it lists is not there, and it is said.
    lone = study.root / 'lone_dicomdir'
    shutil.copytree(study.dir, lone)
    shutil.copy(
        Path(get_testdata_file('MR_small.dcm', download=False)).parent
        / 'dicomdirtests'
        / 'DICOMDIR',
        lone,
    )
    res = read_dicom_dir(lone)
    assert (
        len(res.problems) == 1
        and 'lists 31 image file(s), 31 of them missing' in res.problems[0][1]
    )
    assert len(res.frames) == 33


def test_pydicom_files_beside_a_study_never_take_the_run_down(study):
    """
    Check that scanner/PACS files of other kinds in the folder are reported or listed.

    Scanner/PACS files of other kinds in the folder: refused ones are reported, the readable
    ones of other studies and modalities (MR_small, CT, RT dose) are read, not used, and listed
    once each with the reason, and every frame of the study loads unchanged. Read alone, each
    of those loads in a publishable type.
    """
    root = study.root / 'beside'
    shutil.copytree(study.dir, root / 'study')
    loads = {
        'MR_small.dcm': (np.int16, ['one frame', 'another study']),
        'CT_small.dcm': (np.int16, ['modality CT', 'another study']),
        'rtdose_1frame.dcm': (np.uint32, ['modality RTDOSE', 'another study']),
    }
    refused = {
        'examples_rgb_color.dcm': 'colour image',
        'examples_palette.dcm': 'colour image',
        'examples_ybr_color.dcm': 'NumberOfFrames 30',
        'rtdose.dcm': 'NumberOfFrames 15',
        'liver_1frame.dcm': 'BitsAllocated 1',
        'SC_rgb_jpeg.dcm': 'colour image',
        'image_dfl.dcm': 'missing geometry',
        'JPEG-lossy.dcm': 'missing geometry',
        'MR_small_RLE.dcm': 'duplicate instance',
    }  # decoded, then the same SOP as MR_small's
    for name in [*loads, *refused]:
        shutil.copy(get_testdata_file(name, download=False), root / name)
    res = read_dicom_dir(root)
    why = dict(res.problems)
    assert sorted(why) == sorted(str(root / n) for n in [*refused, *loads])
    for name, part in refused.items():
        assert part in why[str(root / name)], (name, why[str(root / name)])
    for name, (_, parts) in loads.items():
        reason = why[str(root / name)]
        assert 'not used' in reason and all(p in reason for p in parts), reason
    assert res.study_uid == study.ref.study_uid and res.complete and res.left_out == []
    assert sorted(map(_key, res.frames)) == sorted(map(_key, study.ref.frames))
    got = frames_by_path(res)
    for p in study.paths:
        assert np.array_equal(
            got[str(root / 'study' / p.relative_to(study.dir))].image, study.by_path[str(p)].image
        )
    _assert_publishable(res)
    for name, (stored, _) in loads.items():
        alone = study.root / f'alone_{name}'
        alone.mkdir()
        shutil.copy(root / name, alone)
        res = read_dicom_dir(alone)
        assert res.problems == [] and 'no MR cine' in res.choice
        assert pydicom.dcmread(alone / name).pixel_array.dtype == stored
        img = res.frames[0].image
        assert img.dtype == np.float32 and np.array_equal(img, _expected(alone / name))
        _assert_publishable(res)
