"""What may enter the filter: the UWB gate, the IMU check, the IMU's intrinsic corrections."""
