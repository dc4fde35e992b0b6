"""Offline tools: simulator, dataset importers, scoring and the comparison report."""
