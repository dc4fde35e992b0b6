"""The filter state's layout, written once: setup.py generates the C core's ``_layout.h`` from
this file at build time, so the two cannot disagree (docs/ekf.md §1).

The error state: the core's 15 blocks, then the range model's states. The nominal state in
the C core's memory (``state.CoreEskf`` takes its views from the same table): position,
velocity, attitude (w, x, y, z), the biases, then the range model's states from
``NOMINAL_AUX``; the covariance follows them.
"""

P_, V_, TH_, BG_, BA_ = slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12), slice(12, 15)
N_CORE = 15  # position, velocity, attitude, gyro bias, accelerometer bias
NOMINAL = {"p": (0, 3), "v": (3, 6), "q": (6, 10), "b_g": (10, 13), "b_a": (13, 16)}
NOMINAL_AUX = 16
# the IMU front's numbers (checks.imu_check.new_imu_check hands them to the C core in this
# order): its screen's limits, then the maps of checks.intrinsics.BodyMaps, field by field
# (a matrix row-major), with how many numbers each takes
IMU_LIMITS = ("acc_clip", "gyro_clip", "max_acc_jump", "max_gyro_jump", "max_jump_run")
IMU_MAPS = {"acc_M": 9, "acc_b": 3, "gyro_M": 9, "gyro_b": 3, "gyro_offset": 3, "gyro_band": 1}
# State.range_check's output for k ranges: each block k × its numbers per range, in this
# order (the unit vectors anchor → antenna, the innovations, the single-fault estimates and
# their weights; measurements.range_check reads it by the same table)
RANGE_CHECK = {"U": 3, "y": 1, "b": 1, "d": 1}
