"""uwbd: UWB + IMU localisation daemon."""

# the one place the version is written (pyproject.toml reads it from here); a constant,
# not importlib.metadata, whose import alone was a tenth of every command's start-up
__version__ = "0.1.0"
