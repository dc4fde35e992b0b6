"""uwbd's MCAP logs: the file layout, the log sink, replay and recovery."""
