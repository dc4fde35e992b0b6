"""The error state's layout: the core's 15 blocks, then the range model's (docs/ekf.md §1)."""

P_, V_, TH_, BG_, BA_ = slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12), slice(12, 15)
N_CORE = 15  # position, velocity, attitude, gyro bias, accelerometer bias
