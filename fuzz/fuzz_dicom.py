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
atheris target: arbitrary bytes as one file through the DICOM reader's per-file path.

``mlv_ros.core.io.dicom._read_one`` must turn every input into an image or a reason. A finding
is any exception escaping it, a reason from its last-resort handler ("unexpected error …", i.e.
a case the explicit checks miss), or an accepted image that breaks the reader's promises
(2-D, non-empty, at most ``max_pixels``, finite if float).

    python fuzz/fuzz_dicom.py [libFuzzer flags] CORPUS_DIR [SEED_DIR ...]   (see fuzz/README.md)
"""

import logging
import os
import sys
import tempfile

import atheris

with atheris.instrument_imports(include=['pydicom', 'mlv_ros']):
    from mlv_ros.core.io import dicom
    import numpy as np

MAX_PIXELS = 512 * 512
_PATH = os.path.join(tempfile.mkdtemp(prefix='fuzz_dicom_'), 'input.dcm')  # the reader takes paths


def TestOneInput(data: bytes) -> None:
    with open(_PATH, 'wb') as f:
        f.write(data)
    images, why = dicom._read_one(_PATH, MAX_PIXELS)
    if images is None:
        if why.startswith('unexpected error'):
            raise AssertionError(f'reason from the last-resort handler: {why}')
        return
    if not images:
        raise AssertionError('accepted a file with no image')
    for image in images:  # one per frame (Enhanced multi-frame files)
        px = image.pixels
        if px.ndim != 2 or px.size == 0 or px.size > MAX_PIXELS:
            raise AssertionError(f'accepted an image of shape {px.shape}')
        if px.dtype.kind == 'f' and not np.all(np.isfinite(px)):
            raise AssertionError('accepted an image with non-finite pixels')


def main() -> None:
    logging.getLogger('pydicom').setLevel(logging.CRITICAL)  # decoders log each failure at ERROR
    atheris.Setup(sys.argv, TestOneInput)
    atheris.Fuzz()


if __name__ == '__main__':
    main()
