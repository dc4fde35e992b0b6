"""The filter's numbers: the state and its algebra (``eskf.py``, the reference), the C core
that owns the state (``_core.c``, ``_state.c``; ``state.py`` binds it), the UWB-only least
squares, the smoother, rotations."""
