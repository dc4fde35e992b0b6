"""Fusion core: pure numpy, no I/O, no asyncio, no clock."""
