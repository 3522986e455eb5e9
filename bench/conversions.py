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
Benchmark: numpy ⇄ message conversion speed.

Issue: ≤ 5 ms one way for a 256×256 image and a 100k-point cloud. Prints one JSON document; medians
of repeated runs, in milliseconds.
"""

import json
import statistics
import time

from mlv_ros import conversions as cv
import numpy as np
from rclpy.serialization import deserialize_message, serialize_message


def median_ms(fn, repeats=30):
    fn()  # warm up
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t) * 1e3)
    return round(statistics.median(times), 4)


def main():
    rng = np.random.default_rng(0)
    img16 = rng.integers(0, 4096, (256, 256)).astype(np.uint16)
    img32 = rng.normal(size=(256, 256)).astype(np.float32)
    cloud = cv.structured({k: rng.normal(size=100_000) for k in ('x', 'y', 'z', 'dx', 'dy', 'dz')})
    m16, m32, mc = cv.image_to_msg(img16), cv.image_to_msg(img32), cv.cloud_to_msg(cloud)
    naive = np.frombuffer(img16.tobytes(), np.uint8)

    def naive_assign():  # the pitfall: element-wise assignment of a numpy array to uint8[]
        m16.data = naive

    result = {
        'image_256x256_mono16_to_msg_ms': median_ms(lambda: cv.image_to_msg(img16)),
        'image_256x256_mono16_from_msg_ms': median_ms(lambda: cv.msg_to_image(m16)),
        'image_256x256_32FC1_to_msg_ms': median_ms(lambda: cv.image_to_msg(img32)),
        'image_256x256_32FC1_from_msg_ms': median_ms(lambda: cv.msg_to_image(m32)),
        'cloud_100k_6f32_to_msg_ms': median_ms(lambda: cv.cloud_to_msg(cloud)),
        'cloud_100k_6f32_from_msg_ms': median_ms(lambda: cv.msg_to_cloud(mc, ('x', 'y', 'z'))),
        'cloud_100k_cdr_serialize_ms': median_ms(lambda: serialize_message(mc), 10),
        'cloud_100k_cdr_deserialize_ms': median_ms(
            lambda: deserialize_message(serialize_message(mc), type(mc)), 10
        ),
        'naive_numpy_assign_to_uint8_field_ms': median_ms(naive_assign, 5),
    }
    result['naive_vs_fast_ratio'] = round(
        result['naive_numpy_assign_to_uint8_field_ms']
        / max(result['image_256x256_mono16_to_msg_ms'], 1e-6),
        1,
    )
    result['target_ms'] = 5.0
    result['meets_target'] = all(v <= 5.0 for k, v in result.items() if k.endswith('msg_ms'))
    print(json.dumps({'benchmark': 'conversions', 'results': result}, indent=2))


if __name__ == '__main__':
    main()
