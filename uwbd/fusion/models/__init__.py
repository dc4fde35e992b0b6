"""The measurement models: the rows each measurement adds (range, position fix, ZUPT, NHC,
known height); the range's C twin is ``core/mm_range.c``."""
