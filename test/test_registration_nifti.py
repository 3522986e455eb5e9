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

"""NIfTI label volumes as user myocardium masks for the ED registration."""

from mlv_ros.core.registration import masks_for_frames, register_ed
from mlv_ros.core.sim import simulate_study
from mlv_ros.core.types import VIEW_LA, VIEW_SA
import nibabel as nib
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

LPS_RAS = np.array([-1.0, -1.0, 1.0])


def dice(a, b):
    return 2.0 * np.logical_and(a, b).sum() / max(a.sum() + b.sum(), 1)


@pytest.fixture(scope='module')
def study():
    st = simulate_study('normal', snr=20, quick=True, num_phases=2)
    return st, [f for f in st.frames if f.phase_index == 0]


def heart_box(st):
    pts = [
        st.geometries[k].pixel_to_patient(np.argwhere(m).astype(float))
        for k, m in st.ed_masks.items()
    ]
    p = np.concatenate(pts)
    return 0.5 * (p.min(0) + p.max(0)), float(np.max(p.max(0) - p.min(0)))


def voxelise(st, axes_lps, spacing, centre_lps, shape, dtype=np.int16):
    """
    Build an ACDC-style label volume on a grid with the given LPS axes and centre.

    ACDC-style label volume (2 myocardium, 3 LV blood) on a grid whose voxel axes are the unit
    LPS vectors ``axes_lps`` (columns), centred on ``centre_lps``; NIfTI affine in RAS.
    """
    spacing, shape = np.asarray(spacing, float), np.asarray(shape)
    M_lps = axes_lps * spacing  # voxel step -> LPS mm
    origin_lps = centre_lps - M_lps @ ((shape - 1) / 2.0)
    ijk = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing='ij'), -1).reshape(-1, 3)
    X = origin_lps + ijk @ M_lps.T
    lab = np.zeros(len(X), dtype=dtype)
    lab[st.motion.inside_blood(X)] = 3
    lab[st.motion.inside_myocardium(X)] = 2
    aff = np.eye(4)
    aff[:3, :3] = LPS_RAS[:, None] * M_lps  # RAS = diag(-1,-1,1) · LPS
    aff[:3, 3] = LPS_RAS * origin_lps
    return nib.Nifti1Image(lab.reshape(tuple(shape)), aff)


@pytest.fixture(scope='module')
def oblique(study, tmp_path_factory):
    """Oblique (rotated) anisotropic 1.2 x 1.5 x 1.35 mm volume, saved as .nii.gz."""
    st, _ = study
    centre, size = heart_box(st)
    R = Rotation.from_euler('zyx', [25, -35, 50], degrees=True).as_matrix()
    spacing = np.array([1.2, 1.5, 1.35])
    shape = np.ceil((size + 20) / spacing).astype(int)
    img = voxelise(st, R, spacing, centre, shape)
    path = tmp_path_factory.mktemp('nifti') / 'ed_seg.nii.gz'
    nib.save(img, str(path))
    return path


def test_oblique_volume_masks_match_ground_truth(study, oblique):
    st, ed = study
    masks, reasons = masks_for_frames(oblique, ed, label=2)
    assert not reasons, reasons
    assert set(masks) == set(st.ed_masks)
    for k, m in masks.items():
        assert m.dtype == bool and m.shape == st.ed_masks[k].shape
        assert dice(m, st.ed_masks[k]) >= 0.85, (k, dice(m, st.ed_masks[k]))
    # the LV-cavity label of the same volume lies inside the epicardium, never on the wall
    blood, _ = masks_for_frames(oblique, ed, label=3)
    k = (VIEW_SA, 3)
    assert dice(blood[k], st.ed_masks[k]) < 0.1


def test_register_ed_with_nifti_masks(study, oblique):
    st, ed = study
    masks, _ = masks_for_frames(str(oblique), ed)
    res = register_ed(ed, num_particles=1500, masks=masks)
    used = [r for r in res.slice_reports if r.ok]
    assert sum(r.source == 'mask' for r in used) >= len(used) - 1
    inside = st.motion.inside_myocardium(res.particles).mean()
    assert inside >= 0.95, inside


def sa_stack(st, ed, shift_mm=0.0):
    """
    Build a stack of 2-D SA label slices, like a cine SA segmentation.

    A stack of 2-D SA label slices (1.3 mm in-plane, one slice per tagged SA plane), like a
    cine SA segmentation; ``shift_mm`` moves it along the SA normal.
    """
    sa = sorted((f for f in ed if f.view == VIEW_SA), key=lambda f: f.slice_index)
    g0, g1 = sa[0].geometry, sa[1].geometry
    gap = float((g1.image_position - g0.image_position) @ g0.normal)
    axes = np.stack([g0.column_direction, g0.row_direction, g0.normal * np.sign(gap)], 1)
    rows, cols = sa[0].image.shape
    centre = (
        g0.pixel_to_patient(np.array([(rows - 1) / 2, (cols - 1) / 2]))
        + 0.5 * (len(sa) - 1) * gap * g0.normal
        + shift_mm * g0.normal
    )
    return voxelise(
        st,
        axes,
        [g0.row_spacing, g0.column_spacing, abs(gap)],
        centre,
        (rows, cols, len(sa)),
        dtype=np.uint8,
    ), abs(gap)


def test_slice_stack_serves_parallel_planes_only(study):
    st, ed = study
    img, gap = sa_stack(st, ed)
    assert gap > 6.0
    masks, reasons = masks_for_frames(img, ed)
    sa_keys = {k for k in st.ed_masks if k[0] == VIEW_SA}
    assert set(masks) == sa_keys
    for k in sa_keys:
        assert dice(masks[k], st.ed_masks[k]) >= 0.85
    la = {k for k in st.ed_masks if k[0] == VIEW_LA}
    assert set(reasons) == la and all('crosses' in reasons[k] for k in la)
    # a generous tolerance accepts the LA staircase
    loose, _ = masks_for_frames(img, ed, max_distance_mm=gap)
    assert la <= set(loose)
    # the stack moved half a slice gap off the tagged planes: no SA plane is close enough
    off, why = masks_for_frames(sa_stack(st, ed, shift_mm=0.5 * gap)[0], ed)
    assert not any(k[0] == VIEW_SA for k in off)
    assert all('parallel' in why[k] for k in sa_keys)


def test_planes_outside_or_without_label(study):
    st, ed = study
    centre, _ = heart_box(st)
    far = voxelise(st, np.eye(3), [2.0, 2.0, 2.0], centre + np.array([0, 0, 400.0]), (8, 8, 8))
    data = np.zeros((8, 8, 8), np.int16)
    data[0, 0, 0] = 2
    masks, reasons = masks_for_frames(nib.Nifti1Image(data, far.affine), ed)
    assert not masks and set(reasons) == set(st.ed_masks)
    assert all('outside' in r for r in reasons.values())
    # a volume covering the heart with the label only in a far corner: empty masks
    img = voxelise(st, np.eye(3), [4.0, 4.0, 4.0], centre, (40, 40, 40))
    d = np.asanyarray(img.dataobj).copy()
    d[d == 2] = 0
    d[0, 0, 0] = 2
    masks, reasons = masks_for_frames(nib.Nifti1Image(d, img.affine), ed)
    assert not masks and all('no voxel with label 2' in r for r in reasons.values())


def test_bad_input(study, tmp_path):
    _, ed = study
    aff = np.diag([2.0, 2.0, 2.0, 1.0])
    with pytest.raises(ValueError, match='missing.nii.gz: no such file'):
        masks_for_frames(tmp_path / 'missing.nii.gz', ed)
    junk = tmp_path / 'junk.nii'
    junk.write_text('not an image at all\n' * 50)
    with pytest.raises(ValueError, match='junk.nii: not a readable NIfTI'):
        masks_for_frames(junk, ed)
    with pytest.raises(ValueError, match='not a NIfTI image'):
        masks_for_frames(np.zeros((4, 4, 4)), ed)
    p4 = tmp_path / 'cine.nii.gz'
    nib.save(nib.Nifti1Image(np.full((4, 4, 4, 3), 2, np.int16), aff), str(p4))
    with pytest.raises(ValueError, match=r'cine.nii.gz: expected a 3-D label volume.*4-D'):
        masks_for_frames(p4, ed)
    pf = tmp_path / 'prob.nii.gz'
    nib.save(nib.Nifti1Image(np.full((4, 4, 4), 0.5, np.float32), aff), str(pf))
    with pytest.raises(ValueError, match='prob.nii.gz: labels must be integers'):
        masks_for_frames(pf, ed)
    pl = tmp_path / 'labels.nii.gz'
    nib.save(
        nib.Nifti1Image(np.array([0, 1, 3] * 21 + [0], np.uint8).reshape(4, 4, 4), aff), str(pl)
    )
    with pytest.raises(
        ValueError, match=r'labels.nii.gz: myocardium label 2 does not occur.*0, 1, 3'
    ):
        masks_for_frames(pl, ed)
    # the same file with label=3 is fine (a tiny volume at the origin: mostly reasons); 4-D
    # with a trailing singleton axis and integral floats are accepted
    masks, reasons = masks_for_frames(pl, ed, label=3)
    assert len(masks) + len(reasons) == len({(f.view, f.slice_index) for f in ed}) and reasons
    ok = nib.Nifti1Image(np.full((4, 4, 4, 1), 2.0, np.float32), aff)
    assert masks_for_frames(ok, ed)[1]
    with pytest.raises(ValueError, match='max_distance_mm'):
        masks_for_frames(ok, ed, max_distance_mm=-1)
