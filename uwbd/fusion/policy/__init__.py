"""The filter's decisions: an epoch's rows fused and their outcomes, health, recovery, the
heading alignment, the start, the mirror side, rest, robust weights, the outputs."""
